"""Portrait Relight: the Blender extension's entry point (register and unregister only).

The repository root is the extension package; everything else lives in ops/ (operators),
ui/ (properties, panel, preferences) and addon/ (the Blender-free engine).

The submodules are imported inside register()/unregister(), not at import time: test runners and
other tools may import this file on its own (pytest does, to set up the root as a package node,
under whatever name the checkout's folder has), and that must not need a parent package."""


def register():
    from . import ops, ui

    ui.register()
    ops.register()


def unregister():
    from . import ops, ui

    ops.unregister()
    ui.unregister()
