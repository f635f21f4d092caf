"""RELIGHT_PT_sequencer: the Relight tab in the sequencer's sidebar (drawing only)."""

import bpy

from ..ops import bridge, preview_light


def _draw_preview(layout, image_name: str, empty_text: str) -> None:
    image = bpy.data.images.get(image_name)
    if image is None:
        layout.label(text=empty_text, icon='INFO')
        return
    layout.template_icon(icon_value=layout.icon(image), scale=6.0)


class RELIGHT_PT_sequencer(bpy.types.Panel):
    """The footage and the buttons; the settings are its sub-panels below."""
    bl_label = "Portrait Relight"
    bl_space_type = 'SEQUENCE_EDITOR'
    bl_region_type = 'UI'
    bl_category = "Relight"

    def draw(self, context):
        layout = self.layout
        draw_footage(layout, context)
        row = layout.row(align=True)
        row.operator("relight.preview_frame", icon='IMAGE_DATA')
        row.operator("relight.relight_strip", icon='LIGHT_SUN')


class _SubPanel:
    """A sub-panel of the Relight tab, laid out as Blender's own properties are: labels on the
    left, values on the right (use_property_split)."""
    bl_space_type = 'SEQUENCE_EDITOR'
    bl_region_type = 'UI'
    bl_category = "Relight"
    bl_parent_id = "RELIGHT_PT_sequencer"
    decorate = False  # keyframe dots, for panels with animatable settings

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = self.decorate
        self.draw_settings(layout, context, context.scene.relight)


class RELIGHT_PT_lighting(_SubPanel, bpy.types.Panel):
    bl_label = "Lighting"
    decorate = True  # rotation and exposure are animatable

    def draw_settings(self, layout, context, settings):
        draw_lighting(layout, settings)


class RELIGHT_PT_quality(_SubPanel, bpy.types.Panel):
    bl_label = "Quality"

    def draw_settings(self, layout, context, settings):
        draw_quality(layout, context, settings)


class RELIGHT_PT_output(_SubPanel, bpy.types.Panel):
    bl_label = "Output"

    def draw_settings(self, layout, context, settings):
        draw_output(layout, settings)


class RELIGHT_PT_source_light(_SubPanel, bpy.types.Panel):
    bl_label = "Source Light"
    bl_options = {'DEFAULT_CLOSED'}

    def draw_settings(self, layout, context, settings):
        _draw_preview(layout, preview_light.SOURCE_IMAGE,
                      "After a run: the source light the network estimated")


def draw_footage(layout, context):
    layout.operator("relight.import_footage", icon='FILE_MOVIE')
    editor = context.scene.sequence_editor
    strip = editor.active_strip if editor else None
    if strip is None:
        layout.label(text="No active strip", icon='ERROR')
    elif strip.type not in bridge.FOOTAGE_TYPES:
        layout.label(text=f"'{strip.name}' is not footage", icon='ERROR')
    else:
        layout.label(text=f"{strip.name}: frames {strip.frame_final_start}-"
                          f"{strip.frame_final_end - 1}", icon='SEQUENCE')


def draw_lighting(layout, settings):
    layout.prop(settings, "light_source")
    if settings.light_source == 'HDRI_FILE':
        layout.prop(settings, "hdri_path")
    elif settings.light_source == 'BUILTIN':
        layout.prop(settings, "builtin_hdri")
    col = layout.column(align=True)
    col.prop(settings, "rotation")
    col.prop(settings, "exposure")
    layout.prop(settings, "camera")
    layout.prop(settings, "subject")
    if settings.light_source in {'LAMPS', 'WORLD_AND_LAMPS'}:
        layout.prop(settings, "subject_radius")
    layout.operator("relight.preview_light", icon='HIDE_OFF')
    _draw_preview(layout, preview_light.TARGET_IMAGE, "Preview the target light map")


def draw_quality(layout, context, settings):
    cards, problems = bridge.scan_models(bridge.models_dir(context))
    if not cards:
        layout.label(text="No model is installed", icon='ERROR')
        layout.label(text="Add one in Preferences > Add-ons > Portrait Relight")
    else:
        layout.prop(settings, "preset")
        col = layout.column(align=True)
        chosen = settings.preset or bridge.default_card(cards).preset
        for card in cards:
            col.label(text=bridge.preset_label(card),
                      icon="CHECKMARK" if card.preset == chosen else "BLANK1")
    for problem in problems[:3]:
        layout.label(text=problem[:90], icon='ERROR')
    layout.prop(settings, "detail_transfer")


def draw_output(layout, settings):
    layout.prop(settings, "output_dir")
    layout.prop(settings, "background")
    layout.prop(settings, "exposure_mode")
    layout.prop(settings, "exr_compression")
    layout.prop(settings, "write_matte")
    layout.prop(settings, "overwrite")
    layout.prop(settings, "use_frame_range")
    if settings.use_frame_range:
        col = layout.column(align=True)
        col.prop(settings, "frame_start")
        col.prop(settings, "frame_end")


classes = (RELIGHT_PT_sequencer, RELIGHT_PT_lighting, RELIGHT_PT_quality, RELIGHT_PT_output,
           RELIGHT_PT_source_light)


register, unregister = bpy.utils.register_classes_factory(classes)
