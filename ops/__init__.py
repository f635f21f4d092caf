"""Blender operators, one per module, the bridge from Blender data to addon/, and the batch run
(``batch``: the headless script's code and the ``blender -c relight`` command)."""

from . import batch, import_footage, preview_frame, preview_light, relight_strip

modules = (import_footage, preview_light, relight_strip, preview_frame, batch)


def register():
    _use_blenders_colour_config()
    for module in modules:
        module.register()


def _use_blenders_colour_config():
    """Colour conversions use the OpenColorIO configuration this Blender uses ($OCIO wins)."""
    import os

    import bpy

    from ..addon import colour

    path = os.path.join(bpy.utils.resource_path('LOCAL'), "datafiles", "colormanagement",
                        "config.ocio")
    colour.use_config(path if os.path.isfile(path) else None)


def unregister():
    for module in reversed(modules):
        module.unregister()
