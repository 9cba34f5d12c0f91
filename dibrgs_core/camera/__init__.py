"""Pinhole cameras (OpenCV convention), the scene frame they imply, orbits and trajectories, Blender conversion and JSON form. NumPy only: Blender's Python imports this package."""
