"""Portrait Relight: the Blender extension's entry point (register and unregister only).

The repository root is the extension package; everything else lives in ops/ (operators),
ui/ (properties, panel, preferences) and addon/ (the Blender-free engine)."""

from . import ops, ui


def register():
    ui.register()
    ops.register()


def unregister():
    ops.unregister()
    ui.unregister()
