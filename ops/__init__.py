"""Blender operators, one per module, and the bridge from Blender data to addon/."""

from . import import_footage, preview_light, relight_strip

modules = (import_footage, preview_light, relight_strip)


def register():
    for module in modules:
        module.register()


def unregister():
    for module in reversed(modules):
        module.unregister()
