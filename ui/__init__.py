"""Sidebar panel, scene properties and add-on preferences: drawing and settings only."""

from . import panel, prefs, props

modules = (props, prefs, panel)


def register():
    for module in modules:
        module.register()


def unregister():
    for module in reversed(modules):
        module.unregister()
