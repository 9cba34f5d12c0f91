"""DIBR-GS Blender add-on (thin bpy layer; the logic lives in dibrgs_core)."""


def register() -> None:
    pass


def unregister() -> None:
    pass
