"""Add-on preferences: where models live and how to run them."""

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from ..ops import bridge

PROVIDERS = (
    ('AUTO', "Automatic", "The fastest available: CUDA, CoreML or DirectML, else the CPU"),
    ('CUDA', "CUDA", "NVIDIA GPUs"),
    ('COREML', "CoreML", "Apple silicon"),
    ('DIRECTML', "DirectML", "GPUs on Windows"),
    ('CPU', "CPU", "Always available"),
)


class RELIGHT_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = bridge.PACKAGE

    models_dir: StringProperty(name="Models Folder", subtype='DIR_PATH', default="",
                               description="Folder of .onnx models with their .json cards; "
                                           "empty uses the models shipped with the extension")
    provider: EnumProperty(name="Run On", items=PROVIDERS, default='AUTO')
    threads: IntProperty(name="CPU Threads", default=0, min=0, max=256,
                         description="0 lets onnxruntime choose")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "models_dir")
        row = layout.row()
        row.prop(self, "provider")
        row.prop(self, "threads")
        layout.label(text=f"Models in use: {bridge.models_dir(context)}")


classes = (RELIGHT_AP_preferences,)


register, unregister = bpy.utils.register_classes_factory(classes)
