import json
import sys

import numpy as np
import onnx
import pytest

from addon import contract, engine, lightvec, onnx_graph
from addon.errors import DependencyError, ModelError
from tests.onnx_fixtures import TOY_CLASSES, toy_reference, write_conv_model, write_toy_model


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return write_toy_model(tmp_path_factory.mktemp("toy"))


@pytest.fixture(scope="module")
def session(toy):
    return engine.new_session(toy, threads=1)


def _rewrite_card(model, **changes):
    card = engine.card_path_for(model)
    data = json.loads(card.read_text())
    data.update(changes)
    card.write_text(json.dumps(data))


@pytest.mark.parametrize("h,w", [(1, 1), (7, 13), (30, 45), (64, 64), (3, 200)])
def test_toy_runs_at_any_size_through_padding(session, h, w):
    rng = np.random.default_rng(h * 1000 + w)
    img = rng.random((3, h, w)).astype(np.float32)
    light = rng.random(lightvec.SHAPE).astype(np.float32)
    res = session.run_planar(img, light)
    assert res.relit.shape == (3, h, w)
    assert res.parsing.shape == (len(TOY_CLASSES), h, w)
    assert res.source_light.shape == lightvec.SHAPE
    np.testing.assert_allclose(res.relit, toy_reference(img, light), rtol=1e-5, atol=1e-7)
    assert np.all((res.parsing >= 0) & (res.parsing <= 1))


def test_the_toy_really_needs_its_stride(toy):
    # Without the engine's padding the toy cannot keep its parsing the input's size.
    import onnxruntime as ort
    raw = ort.InferenceSession(str(toy), providers=["CPUExecutionProvider"])
    out = raw.run(None, {contract.INPUT_IMAGE: np.zeros((1, 3, 30, 45), np.float32),
                         contract.INPUT_LIGHT: np.ones((1, 3, 16, 16), np.float32)})
    assert out[2].shape[2:] != (30, 45)


def test_padding_is_reflective_and_cropped_back(session):
    img = np.arange(3 * 5 * 6, dtype=np.float32).reshape(3, 5, 6)
    prep = session.preprocess_planar(img, lightvec.uniform(1.0))
    x = prep.feeds[contract.INPUT_IMAGE]
    assert x.shape == (1, 3, 8, 8) and (prep.height, prep.width) == (5, 6)
    np.testing.assert_array_equal(x[0, :, 5, :6], img[:, 3])  # row 5 mirrors row 3
    np.testing.assert_array_equal(x[0, :, :5, 6], img[:, :, 4])


def test_twice_the_light_twice_the_output(session):
    img = np.random.default_rng(1).random((3, 16, 24)).astype(np.float32)
    light = lightvec.splat_direction([0.3, 0.2, 1.0], [1.0, 0.5, 0.2])
    a = session.run_planar(img, light).relit
    b = session.run_planar(img, 2 * light).relit
    np.testing.assert_allclose(b, 2 * a, rtol=1e-6)


def test_session_keeps_no_per_call_state(session):
    before = dict(vars(session))
    session.run_planar(np.ones((3, 9, 9), np.float32), lightvec.uniform(1.0))
    assert vars(session) == before


def test_bad_light_is_refused(session):
    from addon.errors import LightingError
    bad = lightvec.uniform(1.0)
    bad[0, 0, 0] = np.nan
    with pytest.raises(LightingError):
        session.run_planar(np.ones((3, 8, 8), np.float32), bad)


def test_missing_model_and_missing_card(tmp_path, toy):
    with pytest.raises(ModelError, match="does not exist"):
        engine.new_session(tmp_path / "nope.onnx")
    lone = tmp_path / "lone.onnx"
    lone.write_bytes(toy.read_bytes())
    with pytest.raises(ModelError, match="no model card"):
        engine.new_session(lone)


def test_checksum_mismatch_is_refused(tmp_path):
    model = write_toy_model(tmp_path)
    data = bytearray(model.read_bytes())
    data[len(data) // 2] ^= 0xFF
    model.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="corrupt"):
        engine.new_session(model)


def test_corrupt_file_with_matching_card_is_a_model_error(tmp_path):
    model = write_toy_model(tmp_path)
    model.write_bytes(b"this is not an onnx file")
    _rewrite_card(model, sha256=engine.file_sha256(model))
    with pytest.raises(ModelError, match="cannot load"):
        engine.new_session(model)


def test_unknown_contract_and_bad_cards_are_refused(tmp_path):
    model = write_toy_model(tmp_path)
    _rewrite_card(model, contract="relight-onnx/99")
    with pytest.raises(ModelError, match="relight-onnx/99"):
        engine.new_session(model)
    model = write_toy_model(tmp_path / "b")
    card = json.loads(engine.card_path_for(model).read_text())
    del card["stride"]
    engine.card_path_for(model).write_text(json.dumps(card))
    with pytest.raises(ModelError, match="stride"):
        engine.new_session(model)
    model = write_toy_model(tmp_path / "c")
    engine.card_path_for(model).write_text("{not json")
    with pytest.raises(ModelError, match="cannot be read"):
        engine.new_session(model)


@pytest.mark.parametrize("changes, says", [
    ({"relit_scale": "s*k"}, "relit_scale"),
    ({"relit_scale": None}, "relit_scale"),
    ({"inputs": {"image": ["N", 3, "H", "W"], "target_light": ["N", 3, 16, 16]}}, "inputs"),
    ({"outputs": [{"name": "relit", "shape": ["N", 3, "H", "W"]}]}, "outputs"),
    ({"stride": "8"}, "stride"),
    ({"classes": "foreground"}, "classes"),
    ({"training": "a note"}, "training"),
    ({"cost": {"cpu": {"per_size": {"512": 38.0}}}}, "cost.cpu"),
    ({"metrics": {"model": {"rmse": "0.04"}}}, "metrics.model"),
    ({"frontier": {"ms": 9.0}}, "frontier"),
    ({"recommended": "yes"}, "recommended"),
])
def test_a_card_not_laid_out_as_the_exporters_write_it_is_refused(tmp_path, changes, says):
    """One card layout: training/run/export.py's (relit brought back by k, inputs and outputs
    as lists, figures where export and bench/frontier.py put them); anything else is a
    ModelError naming what differs, never a card read by guesswork."""
    model = write_toy_model(tmp_path)
    _rewrite_card(model, **changes)
    with pytest.raises(ModelError, match="not laid out as this add-on's exporters") as err:
        engine.load_card(model)
    assert says in str(err.value)


def test_model_that_breaks_the_contract_is_refused(tmp_path):
    model = write_toy_model(tmp_path)
    m = onnx.load(str(model))
    m.graph.output[2].name = "mask"
    m.graph.node[-1].output[0] = "mask"
    model.write_bytes(m.SerializeToString())
    _rewrite_card(model, sha256=engine.file_sha256(model))
    with pytest.raises(ModelError, match="does not follow contract"):
        engine.new_session(model)


def test_card_with_wrong_class_count_is_caught_at_run(tmp_path):
    model = write_toy_model(tmp_path)
    _rewrite_card(model, classes=["foreground", "skin", "hair"])
    s = engine.new_session(model)
    with pytest.raises(ModelError, match="returned shapes"):
        s.run_planar(np.ones((3, 8, 8), np.float32), lightvec.uniform(1.0))


def test_provider_choice():
    prefs = engine.choose_providers
    assert prefs(["CPUExecutionProvider", "CUDAExecutionProvider"]) == [
        "CUDAExecutionProvider", "CPUExecutionProvider"]
    assert prefs(["CPUExecutionProvider", "CoreMLExecutionProvider", "DmlExecutionProvider"]) == [
        "CoreMLExecutionProvider", "DmlExecutionProvider", "CPUExecutionProvider"]
    assert prefs(["CPUExecutionProvider", "CUDAExecutionProvider"],
                 ["CPUExecutionProvider"]) == ["CPUExecutionProvider"]
    assert prefs(["CPUExecutionProvider"], ["CUDAExecutionProvider"]) == ["CPUExecutionProvider"]
    assert prefs(["AzureExecutionProvider", "CPUExecutionProvider"]) == ["CPUExecutionProvider"]


def test_session_options_are_explicit():
    import onnxruntime as ort
    so = engine.session_options(ort, threads=3, spin=False)
    assert so.intra_op_num_threads == 3 and so.inter_op_num_threads == 1
    assert so.graph_optimization_level == ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    assert so.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert so.get_session_config_entry("session.intra_op.allow_spinning") == "0"


def test_missing_onnxruntime_is_a_dependency_error(monkeypatch, toy):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(DependencyError, match="onnxruntime"):
        engine.new_session(toy)


def test_conv_model_has_the_requested_cost_and_contract(tmp_path):
    model = write_conv_model(tmp_path, gflops_at_512=0.2, name="small")
    card = json.loads(model.with_suffix(".json").read_text())
    assert 0.2 <= card["architecture"]["gflop_per_frame"]["512"] < 0.35
    s = engine.new_session(model, threads=1)
    res = s.run_planar(np.random.default_rng(0).random((3, 20, 36)).astype(np.float32),
                       lightvec.uniform(1.0))
    assert res.relit.shape == (3, 20, 36) and np.all(np.isfinite(res.relit))
    assert res.parsing.shape == (len(contract.PARSING_CLASSES), 20, 36)
    assert np.all(res.source_light >= 0)


def test_a_channels_last_image_is_refused(session):
    with pytest.raises(ValueError, match=r"\(3, H, W\)"):
        session.run_planar(np.ones((7, 13, 3), np.float32), lightvec.uniform(1.5))


def _save_with_external_weights(folder, threshold=100):
    """The toy model saved with its larger weights in a file beside the .onnx, and a card whose
    checksum matches the .onnx (all a card can cover)."""
    model = write_toy_model(folder)
    m = onnx.load(str(model))
    onnx.save_model(m, str(model), save_as_external_data=True, all_tensors_to_one_file=True,
                    location="toy.weights", size_threshold=threshold)
    _rewrite_card(model, sha256=engine.file_sha256(model))
    return model


def test_model_with_external_weight_files_is_refused(tmp_path):
    model = _save_with_external_weights(tmp_path)
    weights = tmp_path / "toy.weights"
    assert weights.is_file()
    assert onnx_graph.external_tensors(model.read_bytes()) == ["w_front"]
    with pytest.raises(ModelError, match="separate files") as err:
        engine.new_session(model)
    assert "w_front" in str(err.value)
    # Altered weights (the case the checksum cannot see) are refused just the same.
    weights.write_bytes(bytes(len(weights.read_bytes())))
    with pytest.raises(ModelError, match="separate files"):
        engine.new_session(model)


def test_external_data_is_found_in_subgraphs_and_constants():
    from onnx import TensorProto, helper, numpy_helper

    big = numpy_helper.from_array(np.ones(64, np.float32), "w")
    big.data_location = TensorProto.EXTERNAL
    entry = big.external_data.add()
    entry.key, entry.value = "location", "w.bin"
    big.ClearField("raw_data")
    inner = helper.make_graph([helper.make_node("Constant", [], ["c"], value=big)], "inner",
                              [], [helper.make_tensor_value_info("c", TensorProto.FLOAT, [64])])
    outer = helper.make_graph(
        [helper.make_node("If", ["cond"], ["y"], then_branch=inner, else_branch=inner)],
        "outer", [helper.make_tensor_value_info("cond", TensorProto.BOOL, [])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [64])])
    data = helper.make_model(outer).SerializeToString()
    assert onnx_graph.external_tensors(data) == ["w", "w"]
    assert onnx_graph.external_tensors(
        helper.make_model(helper.make_graph([], "g", [], [])).SerializeToString()) == []
    with pytest.raises(ValueError):
        onnx_graph.external_tensors(data[:-3])


def test_shipped_and_toy_models_keep_their_weights_inside(toy):
    import pathlib

    for path in [toy, *sorted(pathlib.Path(engine.__file__).parents[1].glob("models/*.onnx"))]:
        assert onnx_graph.external_tensors(path.read_bytes()) == [], path


def test_a_deeply_nested_card_is_a_model_error_not_a_crash(tmp_path):
    model = write_toy_model(tmp_path)
    engine.card_path_for(model).write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(ModelError, match="nested too deeply"):
        engine.load_card(model)
    card = json.loads(engine.card_path_for(write_toy_model(tmp_path / "b")).read_text())
    nested = {}
    card["metrics"] = nested
    for _ in range(500):  # parses, but the panel's readers would recurse 500 levels
        nested["x"] = nested = {}
    engine.card_path_for(model).write_text(json.dumps(card))
    with pytest.raises(ModelError, match="levels deep"):
        engine.load_card(model)


def test_a_cards_figures_are_read_where_export_and_the_frontier_put_them(tmp_path):
    """Time per frame: bench/frontier.py's whole-path figure, else export's CPU time at the size
    nearest the working size; error: the frontier's RMSE, else the card's held-out RMSE (an
    intrinsic model's once its level is set)."""
    model = write_toy_model(tmp_path)
    card = engine.load_card(model)
    assert card.timing == (None, "") and card.held_out_error == (None, "")
    assert card.summary == "time not measured, error not measured"
    _rewrite_card(model, working_size=384,
                  cost={"cpu": {"per_size": {"256": {"ms": 9.5}, "512": {"ms": 38.25}}}},
                  metrics={"model": {"rmse": 0.0412, "rmse_level_fit": 0.03}})
    card = engine.load_card(model)
    assert card.timing == (9.5, "256 px, CPU") and card.ms_per_frame == 9.5
    assert card.held_out_error == (0.0412, "RMSE")
    assert card.summary == "10 ms/frame (256 px, CPU), held-out RMSE 0.0412"
    _rewrite_card(model, frontier={"ms_per_frame": 12.25, "rmse": 0.05, "working_size": 128,
                                   "provider": "CPUExecutionProvider"})
    card = engine.load_card(model)
    assert card.timing == (12.25, "128 px, CPU") and card.held_out_error == (0.05, "RMSE")


def test_a_card_names_its_preset_for_people_and_may_be_the_recommended_one(tmp_path):
    model = write_toy_model(tmp_path)
    card = engine.load_card(model)
    assert (card.title, card.recommended) == ("Toy", False)
    _rewrite_card(model, preset="final-int8", recommended=True)
    card = engine.load_card(model)
    assert (card.title, card.recommended) == ("Final (int8)", True)


def test_an_intrinsic_cards_error_is_the_one_at_the_right_level():
    import pathlib

    card = engine.load_card(pathlib.Path(engine.__file__).parents[1] / "models" /
                            "relight-portrait.onnx")
    error, name = card.held_out_error
    assert name == "RMSE at the right level"
    assert error == card.data["metrics"]["model"]["rmse_level_fit"]
