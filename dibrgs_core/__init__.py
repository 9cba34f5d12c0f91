"""DIBR-GS core library: sparse-view neural Gaussians for remote-sensing scenes.

Importing this package (and ``camera``, ``common``, ``data.scene``, ``data.levir``, ``bridge``,
``training.config``) does not import torch, so Blender's Python can use those modules in-process.
"""
__version__ = "0.1.0"
