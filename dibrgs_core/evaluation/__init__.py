"""Evaluation of a trained run: held-out metrics, LPIPS from local weights, 3DGS PLY export."""
