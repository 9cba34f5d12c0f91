"""Gaussian models: the protocol every model meets (Gaussians for a camera), Scaffold-style neural Gaussians, vanilla 3DGS, IBR reference features. Models know nothing of training."""
