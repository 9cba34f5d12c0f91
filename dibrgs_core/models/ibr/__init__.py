"""IBR reference features (paper: IBR Feature Extraction): weight-free pyramid, DINO ResNet-50 and ViT-B/8 backbones, and the per-anchor feature module."""
