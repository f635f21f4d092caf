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
_offered: list = []  # Blender needs the dynamic items kept alive while it shows them


def installed_providers() -> set[str]:
    """The execution providers the installed onnxruntime has ('CPU' at least)."""
    from ..addon.engine import import_onnxruntime
    from ..addon.errors import DependencyError

    try:
        have = set(import_onnxruntime().get_available_providers())
    except DependencyError:
        have = set()
    return {key for key, names in bridge.ORT_PROVIDERS.items() if names[0] in have} | {'CPU'}


def provider_items(self, context):
    """Automatic and the providers this onnxruntime has; the numbers stay those of PROVIDERS,
    so a saved choice keeps its meaning."""
    if not _offered:
        have = installed_providers()
        _offered.extend((key, name, text, i) for i, (key, name, text) in enumerate(PROVIDERS)
                        if key == 'AUTO' or key in have)
    return _offered


class RELIGHT_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = bridge.PACKAGE

    models_dir: StringProperty(name="Models Folder", subtype='DIR_PATH', default="",
                               description="Folder of .onnx models with their .json cards; "
                                           "empty uses the models shipped with the extension")
    provider: EnumProperty(name="Run On", items=provider_items, default=0,
                           description="Where the network runs: only the execution providers "
                                       "of the installed onnxruntime are offered")
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
