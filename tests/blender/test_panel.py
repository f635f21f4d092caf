"""The sidebar panel and the preferences: what an artist reads about models and light."""

import json

import bpy
import pytest

from conftest import footage_scene


class FakeLayout:
    """Records what a panel draws (the real UILayout exists only inside a drawing region)."""

    def __init__(self, log=None):
        self.log = [] if log is None else log

    def _child(self, *args, **kwargs):
        return FakeLayout(self.log)

    box = row = column = split = _child

    def label(self, text="", icon='NONE'):
        self.log.append(("label", text, icon))

    def prop(self, data, name, **kwargs):
        assert hasattr(data, name), name                  # a typo would fail in Blender too
        self.log.append(("prop", name))

    def operator(self, idname, **kwargs):
        self.log.append(("operator", idname))

    def template_icon(self, icon_value=0, scale=1.0):
        self.log.append(("icon", icon_value))

    def icon(self, data):
        return 1

    def texts(self):
        return [e[1] for e in self.log if e[0] == "label"]


def draw_panel():
    """Everything the Relight tab draws: the main panel, then its sub-panels, open."""
    from portrait_relight.ui import panel

    layout = FakeLayout()
    for cls in panel.classes:
        layout.use_property_split = layout.use_property_decorate = None
        cls.draw(stand_in(cls, layout), bpy.context)
        layout.log.append(("split", cls.__name__, layout.use_property_split,
                           layout.use_property_decorate))
    return layout


def stand_in(cls, layout):
    """An object to call ``cls.draw`` on (a bpy Panel cannot be made outside a region)."""
    methods = {k: getattr(cls, k) for k in dir(cls) if k.startswith(("draw_", "decorate"))}
    return type("P", (), {"layout": layout, **methods})()


@pytest.fixture
def prefs(extension):
    addon = bpy.context.preferences.addons.new()
    addon.module = "portrait_relight"
    yield addon.preferences
    bpy.context.preferences.addons.remove(addon)


def card_with_figures(folder):
    """The toy card with metrics and cost laid out as training/run/export.py writes them."""
    card_path = next(folder.glob("*.json"))
    card = json.loads(card_path.read_text())
    card["metrics"] = {"model": {"rmse": 0.0412, "psnr": 27.7, "ssim": 0.91},
                       "identity": {"rmse": 0.2}, "split": "test"}
    card["cost"] = {"cpu": {"provider": "CPUExecutionProvider",
                            "per_size": {"256": {"ms": 9.5}, "512": {"ms": 38.25}}}}
    card["working_size"] = 512
    card_path.write_text(json.dumps(card))


def test_settings_sit_in_sub_panels_laid_out_as_blenders_own(extension, tmp_path):
    from portrait_relight.ui import panel

    footage_scene(tmp_path, count=2)
    log = draw_panel().log
    splits = {e[1]: e[2:] for e in log if e[0] == "split"}
    assert splits.pop("RELIGHT_PT_sequencer") == (None, None)  # footage and the buttons
    assert splits == {"RELIGHT_PT_lighting": (True, True),      # rotation, exposure animate
                      "RELIGHT_PT_quality": (True, False), "RELIGHT_PT_output": (True, False),
                      "RELIGHT_PT_source_light": (True, False)}
    assert all(cls.bl_parent_id == "RELIGHT_PT_sequencer" for cls in panel.classes[1:])
    drawn = [e[1] for e in log if e[0] == "prop"]
    assert {"light_source", "preset", "output_dir", "overwrite", "exr_compression"} <= set(drawn)


def test_panel_says_plainly_when_no_model_is_installed(prefs, tmp_path):
    prefs.models_dir = str(tmp_path / "empty")
    footage_scene(tmp_path, count=2)
    layout = draw_panel()
    assert "No model is installed" in layout.texts()
    assert ("operator", "relight.relight_strip") in layout.log


def test_panel_shows_each_presets_time_and_error(prefs, toy_models, tmp_path):
    import shutil

    models = tmp_path / "models"
    shutil.copytree(toy_models, models)
    card_with_figures(models)
    prefs.models_dir = str(models)
    footage_scene(tmp_path, count=2)
    texts = draw_panel().texts()
    assert "Toy: 38 ms per frame, held-out error 0.0412" in texts


def two_presets(folder, recommended=None):
    """A models folder with the toy as "draft" (fast) and as "portrait" (slow); the card of
    ``recommended`` marked so."""
    from onnx_fixtures import write_toy_model

    for preset, ms in (("draft", 9.5), ("portrait", 120.0)):
        card_path = write_toy_model(folder, preset).with_suffix(".json")
        card = json.loads(card_path.read_text())
        card.update(preset=preset, cost={"cpu": {"per_size": {"64": {"ms": ms}}}})
        if preset == recommended:
            card["recommended"] = True
        card_path.write_text(json.dumps(card))
    return folder


def test_an_empty_preset_is_the_recommended_one_and_the_panel_says_so(prefs, tmp_path):
    from portrait_relight.ops import bridge

    prefs.models_dir = str(two_presets(tmp_path / "models", recommended="portrait"))
    footage_scene(tmp_path, count=2)
    assert bpy.context.scene.relight.preset == ""
    log = draw_panel().log
    assert ("label", "Portrait (recommended): 120 ms per frame, error not measured",
            'CHECKMARK') in log
    assert ("label", "Draft: 10 ms per frame, error not measured", 'BLANK1') in log
    job = bridge.gather_job(bpy.context, bpy.context.scene.sequence_editor.active_strip)
    assert job.model.preset == "portrait"
    bpy.context.scene.relight.preset = "draft"  # a preset chosen is the one used
    assert bridge.gather_job(bpy.context, bpy.context.scene.sequence_editor.active_strip
                             ).model.preset == "draft"


def test_with_no_card_marked_an_empty_preset_is_the_fastest(prefs, tmp_path):
    from portrait_relight.ops import bridge

    prefs.models_dir = str(two_presets(tmp_path / "models"))
    footage_scene(tmp_path, count=2)
    assert ("label", "Draft: 10 ms per frame, error not measured", 'CHECKMARK') in \
        draw_panel().log
    job = bridge.gather_job(bpy.context, bpy.context.scene.sequence_editor.active_strip)
    assert job.model.preset == "draft"


def test_the_shipped_models_recommend_portrait(extension):
    from portrait_relight.ops import bridge

    cards = bridge.model_cards(bridge.BUNDLED_MODELS)
    assert [c.preset for c in cards if c.recommended] == ["portrait"]
    assert bridge.default_card(cards).preset == "portrait"


def test_panel_lists_an_unusable_model_with_its_reason(prefs, toy_models, tmp_path):
    import shutil

    models = tmp_path / "models"
    shutil.copytree(toy_models, models)
    card_path = next(models.glob("*.json"))
    card = json.loads(card_path.read_text())
    card["contract"] = "relight-onnx/99"
    card_path.write_text(json.dumps(card))
    prefs.models_dir = str(models)
    texts = draw_panel().texts()
    assert "No model is installed" in texts
    assert any("relight-onnx/99" in t for t in texts)


def test_panel_names_a_strip_that_is_not_footage(extension, tmp_path):
    footage_scene(tmp_path, count=2)
    strips = bpy.context.scene.sequence_editor.strips
    bpy.context.scene.sequence_editor.active_strip = strips.new_effect("Title", 'TEXT', 3, 1,
                                                                       length=5)
    assert "'Title' is not footage" in draw_panel().texts()


def test_preferences_choose_the_models_folder(prefs, toy_models, tmp_path):
    from portrait_relight.ops import bridge

    assert bridge.models_dir(bpy.context) == bridge.BUNDLED_MODELS
    prefs.models_dir = str(toy_models)
    assert bridge.models_dir(bpy.context) == toy_models
    assert [c.preset for c in bridge.model_cards(bridge.models_dir(bpy.context))] == ["toy"]
    footage_scene(tmp_path, count=2)
    prefs.provider = 'CPU'
    prefs.threads = 1
    job = bridge.gather_job(bpy.context, bpy.context.scene.sequence_editor.active_strip)
    assert job.options.providers == ["CPUExecutionProvider"] and job.options.threads == 1
    assert bpy.ops.relight.relight_strip() == {'FINISHED'}      # no override: the preferences


def test_preferences_offer_only_the_installed_execution_providers(prefs):
    import onnxruntime

    from portrait_relight.ui import prefs as prefs_module

    offered = [item[0] for item in prefs_module.provider_items(prefs, bpy.context)]
    have = set(onnxruntime.get_available_providers())
    assert offered[0] == 'AUTO' and 'CPU' in offered
    assert ('CUDA' in offered) == ("CUDAExecutionProvider" in have)  # this CPU build: no CUDA
    assert ('DIRECTML' in offered) == ("DmlExecutionProvider" in have)
    with pytest.raises(TypeError):
        prefs.provider = 'CUDA' if 'CUDA' not in offered else 'NOT_A_PROVIDER'
    prefs.provider = 'CPU'
    assert prefs.provider == 'CPU'
