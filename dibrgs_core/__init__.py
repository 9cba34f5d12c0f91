"""DIBR-GS core library: sparse-view neural Gaussians for remote-sensing scenes.

Importing this package (and ``cameras``, ``io_levir``, ``errors``, ``report``)
does not import torch, so Blender's Python can use those modules in-process.
"""
__version__ = "0.1.0"
