"""Ranges of numeric options, written once: the command line checks them when it parses its
arguments, the library again when it is called directly. Standard library only."""
from __future__ import annotations

#: ``resolution_scale`` / ``--resolution-scale``: a positive factor, at most 4x upsampling.
MAX_RESOLUTION_SCALE = 4.0
#: Smallest image side (pixels) a run trains on or a generated scene has.
MIN_RESOLUTION = 8
#: Fewest training views a run accepts (SfM, the plane sweep and the IBR features work between views).
MIN_TRAIN_VIEWS = 2
