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
* :mod:`.describe`: ``python -m dibrgs_core.bridge.describe SCENE OUT.json``,
  run by the add-on with the training interpreter so Blender's Python never
  needs pycolmap, PIL or torch to import a scene.

Every module here imports numpy and the standard library only.
"""
