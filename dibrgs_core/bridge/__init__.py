"""Logic behind the Blender add-on that needs no Blender (and no torch).

The add-on (``addon/``) stays a thin bpy layer; what can be tested without
Blender lives here:

* :mod:`.path`: pseudo-view / fly-through cameras sampled from a polyline
  (the evaluated curve), orbit control points.
* :mod:`.progress`: parsing ``dibrgs train --progress-json`` lines.
* :mod:`.compositor`: which compositor API a Blender version has and how the
  result nodes are laid out and wired.
* :mod:`.jobs`: ``dibrgs`` command lines for the chosen interpreter and a
  non-blocking subprocess runner with cancel and a log file.
* :mod:`.checks`: what ``dibrgs check --json`` (the add-on's "Set up / Check")
  reports, folded for display.
* :mod:`.describe`: the scene description the add-on imports, read in
  Blender's own Python (no torch, Pillow or pycolmap): COLMAP models with
  :mod:`.colmap_model`, image sizes from headers with :mod:`.imagesize`.

Every module here imports numpy and the standard library only.
"""
