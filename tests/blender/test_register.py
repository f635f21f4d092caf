"""The extension registers and unregisters cleanly, and follows the house naming."""

import bpy


def test_register_adds_operators_panel_and_settings(extension):
    # bpy.ops.relight.<name> exists for any name; the RNA type exists only once registered.
    for name in ("import_footage", "relight_strip", "preview_light"):
        assert getattr(bpy.ops.relight, name).get_rna_type().identifier == f"RELIGHT_OT_{name}"
    assert "RELIGHT_PT_sequencer" in dir(bpy.types)
    settings = bpy.context.scene.relight
    assert settings.light_source == 'WORLD'
    assert settings.output_dir == "//relit/"


def test_settings_live_under_one_scene_pointer(extension):
    relight_props = [p.identifier for p in bpy.types.Scene.bl_rna.properties
                     if p.identifier.startswith("relight")]
    assert relight_props == ["relight"]


def test_operator_names_follow_house_style(extension):
    from portrait_relight import ops

    for module in ops.modules:
        for cls in module.classes:
            verb_noun = cls.__name__.removeprefix("RELIGHT_OT_")
            assert cls.__name__.startswith("RELIGHT_OT_")
            assert cls.bl_idname == f"relight.{verb_noun}"


def test_unregister_then_register_again(extension):
    extension.unregister()
    try:
        assert not hasattr(bpy.types.Scene, "relight")
        assert "RELIGHT_PT_sequencer" not in dir(bpy.types)
        assert not hasattr(bpy.types, "RELIGHT_OT_relight_strip")
    finally:
        extension.register()
    assert hasattr(bpy.types.Scene, "relight")


def test_register_never_imports_onnxruntime_or_training():
    import subprocess
    import sys

    code = ("import sys, bpy; sys.path.insert(0, 'tests/blender'); "
            "from conftest import load_extension; load_extension().register(); "
            "bad = [m for m in ('onnxruntime', 'torch', 'training') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    from conftest import ROOT
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
