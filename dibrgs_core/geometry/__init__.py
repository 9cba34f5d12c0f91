"""Geometry initialisation (paper: dense initialisation): SfM with known poses, dense depth priors, overlap-free fusion, point-cloud tools, height map and surface, visibility."""
