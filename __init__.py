"""Blender extension entry point: the repository root is the extension root.

Blender imports this package and calls ``register()``/``unregister()``; the
add-on itself lives in ``addon/``.
"""


def register() -> None:
    from .addon import register as _register

    _register()


def unregister() -> None:
    from .addon import unregister as _unregister

    _unregister()
