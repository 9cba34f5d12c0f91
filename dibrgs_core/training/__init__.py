"""Training: configuration and presets, losses, supervised frames, progressive-DIBR pseudo views, checkpoints, the error-against-time curve, the trainer."""
