"""Generated aerial scenes rendered with Blender's bpy (the only library package that imports bpy)."""
