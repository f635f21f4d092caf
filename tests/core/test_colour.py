import pathlib
import re

import numpy as np
import pytest

from addon import colour
from addon.errors import InputError


def test_srgb_curve_known_values_and_round_trip():
    x = np.array([0.0, 0.04045, 0.5, 1.0], np.float32)
    lin = colour.srgb_to_linear(x)
    np.testing.assert_allclose(lin, [0.0, 0.04045 / 12.92, 0.214041, 1.0], rtol=1e-5)
    y = np.linspace(-1, 2, 301).astype(np.float32)
    np.testing.assert_allclose(colour.linear_to_srgb(colour.srgb_to_linear(y)), y, atol=1e-5)


@pytest.mark.parametrize("name", ["sRGB", "Rec.1886", "Linear Rec.709", "Display P3"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_integer_lut_matches_the_float_path(name, dtype):
    space = colour.lookup(name)
    top = np.iinfo(dtype).max
    codes = np.linspace(0, top, 97).astype(dtype).reshape(1, -1, 1).repeat(3, axis=2)
    via_lut = colour.to_linear(codes, space)
    via_float = colour.to_linear(codes.astype(np.float32) / top, space)
    np.testing.assert_allclose(via_lut, via_float, rtol=1e-5, atol=1e-7)


def test_rec1886_is_gamma_2_4():
    out = colour.to_linear(np.full((1, 1, 3), 0.5, np.float32), colour.lookup("Rec.1886"))
    np.testing.assert_allclose(out, 0.5 ** 2.4, rtol=1e-6)


@pytest.mark.parametrize("name", ["Linear Rec.2020", "Linear DCI-P3 D65", "Display P3",
                                  "Rec.2020", "Linear FilmLight E-Gamut"])
def test_d65_white_stays_white(name):
    out = colour.to_linear(np.ones((1, 1, 3), np.float32), colour.lookup(name))
    np.testing.assert_allclose(out, 1.0, atol=2e-4)


def test_xyz_white_points():
    d65 = np.array([[[0.95047, 1.0, 1.08883]]], np.float32)
    np.testing.assert_allclose(colour.to_linear(d65, colour.lookup("Linear CIE-XYZ D65")), 1.0,
                               atol=1e-3)
    e = np.ones((1, 1, 3), np.float32)  # illuminant E white is equal XYZ
    np.testing.assert_allclose(colour.to_linear(e, colour.lookup("Linear CIE-XYZ E")), 1.0,
                               atol=2e-3)


def test_aliases_and_refusals():
    assert colour.lookup("Linear").name == "Linear Rec.709"
    assert colour.lookup("Raw").is_data
    assert colour.lookup("Non-Color").is_data
    with pytest.raises(InputError, match="set the strip's colour space"):
        colour.lookup("no such space")


needs_ocio = pytest.mark.skipif(not colour.ocio_names(), reason="needs OpenColorIO (opencolorio, "
                                "requirements.txt) and Blender's config.ocio (the bpy module)")


@needs_ocio
def test_every_colour_space_of_blenders_config_is_converted():
    names = colour.ocio_names()
    assert len(names) >= 24 and {"ACEScg", "ACES2065-1", "ACEScc", "ACEScct", "AgX Log",
                                 "Filmic Log", "Rec.2100-PQ", "Rec.2100-HLG", "AgX Base sRGB",
                                 "Filmic sRGB"} <= set(names)
    rng = np.random.default_rng(1)
    px = rng.random((4, 5, 3)).astype(np.float32)
    before = px.copy()
    for name in names:
        space = colour.lookup(name)
        out = colour.to_linear(px, space)
        assert out.shape == px.shape and out.dtype == np.float32 and np.isfinite(out).all(), name
        np.testing.assert_array_equal(px, before, err_msg=name)  # never converted in place


@needs_ocio
def test_fast_paths_agree_with_opencolorio():
    """The hand-written paths give OpenColorIO's own results with Blender's config."""
    rng = np.random.default_rng(2)
    # non-negative: below zero the fast sRGB path mirrors the curve, OpenColorIO extends its
    # linear toe (no integer file holds such values)
    px = (rng.random((64, 64, 3)) * 1.2).astype(np.float32)
    for name in colour.SPACES:
        ours = colour.to_linear(px, colour.lookup(name))
        ref = colour.ocio_space(name, colour.config_path())
        theirs = colour.to_linear(px, ref)
        np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=5e-5, err_msg=name)


@needs_ocio
def test_acescg_and_log_spaces_are_scene_light():
    red = colour.to_linear(np.array([[[1.0, 0.0, 0.0]]], np.float32), colour.lookup("ACEScg"))
    # ACEScg (AP1) red in linear Rec.709: the standard AP1 -> Rec.709 matrix's first column
    np.testing.assert_allclose(red[0, 0], [1.7051, -0.1302, -0.0240], atol=2e-3)
    grey = colour.to_linear(np.full((1, 1, 3), 0.4135884, np.float32), colour.lookup("ACEScc"))
    np.testing.assert_allclose(grey, 0.18, rtol=2e-3)  # ACEScc encodes 0.18 as 0.4135884
    white = colour.to_linear(np.ones((1, 1, 3), np.float32), colour.lookup("Rec.2100-PQ"))
    assert float(white.min()) > 10  # PQ's peak is far above diffuse white


@needs_ocio
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_opencolorio_planar_equals_channels_last(dtype):
    rng = np.random.default_rng(3)
    if dtype == np.float32:
        px = rng.random((3, 40, 70)).astype(np.float32)
    else:
        px = rng.integers(0, np.iinfo(dtype).max + 1, (3, 40, 70)).astype(dtype)
    before = px.copy()
    space = colour.lookup("ACEScct")
    got = colour.to_linear_planar(px, space, 0.5)
    want = colour.to_linear(px.transpose(1, 2, 0), space, 0.5).transpose(2, 0, 1)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(px, before)  # the caller's pixels are never changed


def test_config_follows_ocio_variable_then_the_registered_one(monkeypatch, tmp_path):
    monkeypatch.delenv("OCIO", raising=False)
    colour.use_config(tmp_path / "blender.ocio")
    try:
        assert colour.config_path() == str(tmp_path / "blender.ocio")
        monkeypatch.setenv("OCIO", str(tmp_path / "studio.ocio"))
        assert colour.config_path() == str(tmp_path / "studio.ocio")
        with pytest.raises(InputError, match=r"\$OCIO"):
            colour.lookup("ACEScg")  # the studio config does not exist
    finally:
        colour.use_config(None)


def _blender_config():
    """Blender's own colour config inside the bpy wheel (found, not imported)."""
    import importlib.util
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.origin:
        return None
    found = sorted(pathlib.Path(spec.origin).parent.glob("*/datafiles/colormanagement/config.ocio"))
    return found[0] if found else None


def test_matrices_are_blenders_own():
    cfg = _blender_config()
    if cfg is None:
        pytest.skip("needs the bpy module (Blender's config.ocio), which is not installed")
    text = cfg.read_text()
    ours = {"Linear Rec.709": colour.XYZ_TO_REC709, "Linear DCI-P3 D65": colour.XYZ_TO_P3D65,
            "Linear Rec.2020": colour.XYZ_TO_REC2020,
            "Linear FilmLight E-Gamut": colour.XYZ_TO_EGAMUT}
    for name, m in ours.items():
        block = text[text.index(f"name: {name}\n"):]
        nums = re.search(r"MatrixTransform> \{matrix: \[([^\]]*)\]", block).group(1)
        mat = np.array([float(v) for v in nums.split(",")]).reshape(4, 4)[:3, :3]
        np.testing.assert_allclose(m, mat, atol=1e-7, err_msg=name)
    spimtx = np.loadtxt(cfg.parent / "luts" / "xyz_E_to_D65.spimtx")[:, :3]
    np.testing.assert_allclose(colour.XYZ_E_TO_D65, spimtx, atol=1e-8)


@pytest.mark.parametrize("name", ["sRGB", "Linear Rec.709", "Rec.2020"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_planar_conversion_equals_channels_last(name, dtype):
    rng = np.random.default_rng(0)
    if dtype == np.float32:
        px = (rng.random((3, 300, 1000)) * 1.5 - 0.2).astype(np.float32)  # > one lookup band
    else:
        px = rng.integers(0, np.iinfo(dtype).max + 1, (3, 300, 1000)).astype(dtype)
    space = colour.lookup(name)
    got = colour.to_linear_planar(px, space, 0.25)
    want = colour.to_linear(px.transpose(1, 2, 0), space, 0.25).transpose(2, 0, 1)
    assert got.dtype == np.float32 and got.shape == px.shape
    if space.matrix is None:
        np.testing.assert_array_equal(got, want)
    else:  # the gamut matrix product is summed in another order
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"\(3, H, W\)"):
        colour.to_linear_planar(px.transpose(1, 2, 0), space)


@needs_ocio
@pytest.mark.parametrize("name", ["Filmic Log", "ACEScg"])
def test_pipeline_relights_footage_declared_in_an_opencolorio_space(name, tmp_path):
    """8-bit footage declared in a space only OpenColorIO converts: the toy model (relit =
    image x the light's irradiance ratio, its source radiance the clip's exposure s) under
    uniform light 2 doubles the converted input over s."""
    from addon import frames, lightvec, pipeline
    from tests.clip_fixtures import ramp_frames, write_movie
    from tests.onnx_fixtures import write_toy_model

    src = ramp_frames(3)
    movie = str(write_movie(tmp_path / "clip.mov", src, codec="png"))
    toy = str(write_toy_model(tmp_path / "model"))
    clip = pipeline.ClipSpec("movie", movie, (), 0, 3, name, 25.0)
    res = pipeline.relight_clip(clip, 2 * lightvec.uniform(1.0)[None], tmp_path / "out",
                                pipeline.RelightOptions(toy, working_size=32, threads=1,
                                                        background="network",
                                                        exposure_mode="physical"))
    for i, f in enumerate(res.relit_files):
        want = np.maximum(2 * colour.to_linear(src[i], colour.lookup(name)), 0.0)
        want /= res.exposure_scale
        np.testing.assert_allclose(frames.read_exr(f), want, rtol=4e-3,
                                   atol=2e-3 * float(want.max()))
