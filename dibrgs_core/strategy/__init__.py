"""Densification strategies (gsplat style): one interface with pre/post-backward hooks, shared optimiser surgery, Scaffold anchor growth with the height veto, 3DGS clone/split/prune."""
