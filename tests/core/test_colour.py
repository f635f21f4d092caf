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
    for name in ("AgX Base sRGB", "Filmic sRGB", "Filmic Log", "ACEScg", "no such space"):
        with pytest.raises(InputError, match="set the strip's colour space"):
            colour.lookup(name)


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
