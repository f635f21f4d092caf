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
    bl_label = "Portrait Relight"
    bl_space_type = 'SEQUENCE_EDITOR'
    bl_region_type = 'UI'
    bl_category = "Relight"

    def draw(self, context):
        layout = self.layout
        settings = context.scene.relight
        draw_footage(layout, context)
        draw_lighting(layout.box(), settings)
        draw_quality(layout.box(), context, settings)
        draw_output(layout.box(), settings)
        row = layout.row(align=True)
        row.operator("relight.preview_frame", icon='IMAGE_DATA')
        row.operator("relight.relight_strip", icon='LIGHT_SUN')
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


def draw_lighting(box, settings):
    box.label(text="Lighting", icon='WORLD')
    box.prop(settings, "light_source", text="")
    if settings.light_source == 'HDRI_FILE':
        box.prop(settings, "hdri_path")
    elif settings.light_source == 'BUILTIN':
        box.prop(settings, "builtin_hdri")
    col = box.column(align=True)
    col.prop(settings, "rotation")
    col.prop(settings, "exposure")
    box.prop(settings, "camera")
    box.prop(settings, "subject")
    if settings.light_source in {'LAMPS', 'WORLD_AND_LAMPS'}:
        box.prop(settings, "subject_radius")
    row = box.row()
    row.operator("relight.preview_light", icon='HIDE_OFF')
    _draw_preview(box, preview_light.TARGET_IMAGE, "Preview the target light map")


def draw_quality(box, context, settings):
    box.label(text="Quality", icon='SETTINGS')
    cards, problems = bridge.scan_models(bridge.models_dir(context))
    if not cards:
        box.label(text="No model is installed", icon='ERROR')
        box.label(text="Add one in Preferences > Add-ons > Portrait Relight")
    else:
        box.prop(settings, "preset", text="")
        col = box.column(align=True)
        chosen = settings.preset or bridge.default_card(cards).preset
        for card in cards:
            col.label(text=bridge.preset_label(card),
                      icon="CHECKMARK" if card.preset == chosen else "BLANK1")
    for problem in problems[:3]:
        box.label(text=problem[:90], icon='ERROR')
    box.prop(settings, "detail_transfer")


def draw_output(box, settings):
    box.label(text="Output", icon='OUTPUT')
    box.prop(settings, "output_dir", text="")
    box.prop(settings, "background")
    box.prop(settings, "exposure_mode")
    box.prop(settings, "exr_compression")
    row = box.row()
    row.prop(settings, "write_matte")
    row.prop(settings, "overwrite")
    box.prop(settings, "use_frame_range")
    if settings.use_frame_range:
        row = box.row(align=True)
        row.prop(settings, "frame_start")
        row.prop(settings, "frame_end")


classes = (RELIGHT_PT_sequencer,)


register, unregister = bpy.utils.register_classes_factory(classes)
