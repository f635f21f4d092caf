"""Scene settings: everything the artist sets lives under one pointer property, ``Scene.relight``."""

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..ops import bridge

LIGHT_SOURCES = (
    ("WORLD", "World", "The scene world's environment texture (HDRI)"),
    ("LAMPS", "Lamps", "The scene's point, sun, spot and area lamps"),
    ("WORLD_AND_LAMPS", "World and Lamps", "The world HDRI plus the scene's lamps"),
    ("HDRI_FILE", "HDRI File", "An equirectangular HDRI file on disk"),
    ("BUILTIN", "Studio HDRI", "One of Blender's bundled studio HDRIs"),
)

# Paths may be relative to the .blend ("//"); Blender 4.5+ wants that declared.
BLEND_RELATIVE = ({'PATH_SUPPORTS_BLEND_RELATIVE'}
                  if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties
                  else set())

# Enum items built by callbacks must stay referenced from Python, or Blender shows garbage.
_enum_cache = {}


def _builtin_items(self, context):
    names = bridge.builtin_hdri_names()
    items = [(n, n.replace("_", " ").title(), f"Blender's bundled '{n}' HDRI") for n in names]
    _enum_cache["builtin"] = items or [("NONE", "None found", "Blender's studio HDRIs are missing")]
    return _enum_cache["builtin"]


def _preset_search(self, context, edit_text):
    cards = bridge.model_cards(bridge.models_dir(context))
    return [(c.preset, bridge.preset_label(c)) for c in cards
            if edit_text.lower() in c.preset.lower()]


def _is_camera(self, obj):
    return obj.type == 'CAMERA'


class RELIGHT_PG_settings(bpy.types.PropertyGroup):
    light_source: EnumProperty(name="Light", items=LIGHT_SOURCES, default='WORLD',
                               description="Where the target lighting comes from")
    hdri_path: StringProperty(name="HDRI", subtype='FILE_PATH', options=BLEND_RELATIVE,
                              description="Equirectangular HDRI (EXR or HDR)")
    builtin_hdri: EnumProperty(name="Studio HDRI", items=_builtin_items)
    rotation: FloatProperty(name="Rotation", subtype='ANGLE', default=0.0,
                            description="Turns the lighting about the vertical axis (animatable)")
    exposure: FloatProperty(name="Exposure", default=0.0, soft_min=-10.0, soft_max=10.0,
                            description="Scales the lighting by 2^exposure (animatable)")
    subject: PointerProperty(name="Subject", type=bpy.types.Object,
                             description="Where the person stands; empty uses the camera's focus point")
    camera: PointerProperty(name="Camera", type=bpy.types.Object, poll=_is_camera,
                            description="Defines the light frame; empty uses the scene camera")
    subject_radius: FloatProperty(name="Subject Radius", default=0.15, min=0.01, soft_max=2.0,
                                  unit='LENGTH', description="Size of the head, for near lamps")
    # A name, not an enum: the models folder may change between sessions and machines (a farm),
    # and a saved enum index would then silently point at another model.
    preset: StringProperty(name="Quality", default="", search=_preset_search,
                           description="Model preset, each trading accuracy for time; empty "
                                       "uses the recommended model (Portrait where installed)")
    output_dir: StringProperty(name="Output", subtype='DIR_PATH', default="//relit/",
                               options=BLEND_RELATIVE,
                               description="Folder for the relit EXR frames: a sub-folder per strip, "
                                           "holding one take (v001, v002, ...) per lighting")
    write_matte: BoolProperty(name="Matte Strip", default=False,
                              description="Also write the portrait matte and add it as a strip")
    background: EnumProperty(
        name="Background", default='RELIT',
        items=[('NETWORK', "Network", "The network's output everywhere (it repaints the "
                                      "background)"),
               ('KEEP', "Keep", "The relit subject over the footage's own background, as it was "
                                "(by the portrait matte)"),
               ('RELIT', "Keep, Relit", "The relit subject over the footage's own background, "
                                        "brightened and tinted by the change of light as a wall "
                                        "facing the camera")],
        description="What stands behind the relit subject")
    exposure_mode: EnumProperty(
        name="Exposure", default='KEEP',
        items=[('KEEP', "Keep Footage's", "The subject keeps the footage's overall exposure: "
                                          "the light sets direction, colour and contrast (one "
                                          "gain for the clip, so an animated light still "
                                          "brightens and dims it)"),
               ('PHYSICAL', "Physical", "Absolute units, for scenes lit to scale: a lamp's "
                                        "watts and distance set the brightness")],
        description="How bright the relit subject is")
    exr_compression: EnumProperty(
        name="Compression", default='PIZ',
        items=[('PIZ', "PIZ", "Lossless wavelet compression: the smallest files for noisy "
                              "footage"),
               ('ZIP', "ZIP", "Lossless, in blocks of 16 lines"),
               ('ZIPS', "ZIP (single line)", "Lossless, line by line"),
               ('RLE', "RLE", "Lossless run-length: fast, little saving on footage"),
               ('NONE', "None", "Uncompressed: the fastest to write, the largest files")],
        description="Compression of the relit EXR frames (all lossless)")
    detail_transfer: BoolProperty(name="Keep Fine Detail", default=True,
                                  description="Bring the footage's full-resolution detail back "
                                              "into the relit frames")
    # Named "overwrite" as in earlier versions' files and the batch script's --overwrite.
    overwrite: BoolProperty(name="Replace Latest Take", default=False,
                            description="When the lighting or settings changed, relight into the "
                                        "strip's latest take, replacing its frames and strip, "
                                        "instead of making a new take (the same lighting and "
                                        "settings resume their take either way)")
    use_frame_range: BoolProperty(name="Frame Range", default=False,
                                  description="Relight only these scene frames (render farm chunks)")
    frame_start: IntProperty(name="Start", default=1)
    frame_end: IntProperty(name="End", default=250)


classes = (RELIGHT_PG_settings,)


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    bpy.types.Scene.relight = PointerProperty(type=RELIGHT_PG_settings)


def unregister():
    del bpy.types.Scene.relight
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
