"""Reading HDRI files: OpenEXR and Radiance RGBE (flat and run-length encoded), and bad files."""


import numpy as np
import OpenEXR
import pytest

from addon import hdri, hdri_io
from addon.errors import InputError


def _image(h=8, w=16):
    rng = np.random.default_rng(3)
    img = rng.gamma(0.7, 1.0, (h, w, 3)).astype(np.float32)
    img[2, 5] = [5000.0, 2000.0, 100.0]  # a sun
    img[3, 3] = 0.0
    return img


def _to_rgbe(rgb):
    """Radiance's float -> RGBE encoding (frexp of the largest channel)."""
    m = rgb.max(axis=-1)
    mant, exp = np.frexp(m)
    scale = np.where(m > 1e-32, mant * 256.0 / np.where(m > 0, m, 1), 0.0)
    out = np.zeros(rgb.shape[:2] + (4,), np.uint8)
    out[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    out[..., 3] = np.where(m > 1e-32, exp + 128, 0)
    return out


def _rle_channel(values):
    """New-style Radiance run-length encoding of one channel of one scanline."""
    out, i, n = bytearray(), 0, len(values)
    while i < n:
        run = 1
        while i + run < n and run < 127 and values[i + run] == values[i]:
            run += 1
        if run >= 3:
            out += bytes([128 + run, values[i]])
            i += run
        else:
            j = i
            while j < n and j - i < 128 and not (
                    j + 2 < n and values[j] == values[j + 1] == values[j + 2]):
                j += 1
            out += bytes([j - i]) + bytes(values[i:j])
            i = j
    return bytes(out)


def _write_hdr(path, rgb, rle=False, header_extra=b"", resolution=None):
    rgbe = _to_rgbe(rgb)
    h, w = rgb.shape[:2]
    body = bytearray()
    for row in rgbe:
        if rle:
            body += bytes([2, 2, w >> 8, w & 255])
            for ch in range(4):
                body += _rle_channel(row[:, ch].tolist())
        else:
            body += row.tobytes()
    res = resolution or f"-Y {h} +X {w}".encode()
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n" + header_extra + b"\n" + res + b"\n"
                     + bytes(body))
    return path


def _write_exr(path, rgb, half=False, layout="RGB"):
    data = rgb.astype(np.float16 if half else np.float32)
    if layout == "RGB":
        channels = {"RGB": np.ascontiguousarray(data)}
    else:
        channels = {c: np.ascontiguousarray(data[..., i]) for i, c in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))
    return path


@pytest.mark.parametrize("half,layout", [(False, "RGB"), (True, "RGB"), (False, "split")])
def test_exr_round_trip(tmp_path, half, layout):
    img = _image()
    got = hdri_io.read_hdri(_write_exr(tmp_path / "a.exr", img, half, layout))
    assert got.dtype == np.float32 and got.shape == img.shape and got.flags.c_contiguous
    np.testing.assert_allclose(got, img, rtol=1e-3 if half else 0)


@pytest.mark.parametrize("rle", [False, True])
def test_radiance_round_trip_within_rgbe_precision(tmp_path, rle):
    img = _image(8, 16)
    got = hdri_io.read_hdri(_write_hdr(tmp_path / "a.hdr", img, rle=rle))
    assert got.dtype == np.float32 and got.shape == img.shape
    # RGBE keeps 8 bits of mantissa relative to the brightest channel of each pixel.
    tol = img.max(axis=-1, keepdims=True) / 128
    assert np.all(np.abs(got - img) <= tol)
    assert np.all(got[3, 3] == 0)


def test_radiance_flips_and_exposure(tmp_path):
    img = _image(8, 16)
    plain = hdri_io.read_hdri(_write_hdr(tmp_path / "a.hdr", img))
    flipped = hdri_io.read_hdri(_write_hdr(tmp_path / "b.hdr", img[::-1], resolution=b"+Y 8 +X 16"))
    np.testing.assert_array_equal(plain, flipped)
    exposed = hdri_io.read_hdri(_write_hdr(tmp_path / "c.hdr", img, header_extra=b"EXPOSURE=2\n"))
    np.testing.assert_allclose(exposed, plain / 2, rtol=1e-6)


def test_radiance_file_feeds_the_downsampler(tmp_path):
    img = np.ones((64, 128, 3), np.float32)
    light = hdri.downsample(hdri_io.read_hdri(_write_hdr(tmp_path / "u.hdr", img, rle=True)))
    # RGBE stores 1 as 1 + half a step.
    np.testing.assert_allclose(light, 1.0 + 0.5 / 128, rtol=1e-6)


@pytest.mark.parametrize("name,content,match", [
    ("missing.exr", None, "not found"),
    ("a.png", b"\x89PNG", "OpenEXR"),
    ("bad.exr", b"not an exr at all", "damaged"),
    ("bad.hdr", b"hello", "not a Radiance"),
    ("xyz.hdr", b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 2 +X 4\n" + bytes(32), "RGBE"),
    ("odd.hdr", b"#?RADIANCE\n\n+X 4 -Y 2\n" + bytes(32), "resolution"),
    ("short.hdr", b"#?RADIANCE\n\n-Y 2 +X 4\n" + bytes(20), "truncated"),
    ("badrle.hdr", b"#?RADIANCE\n\n-Y 1 +X 8\n" + bytes([2, 2, 0, 8, 200, 1]) + bytes(10),
     "run-length"),
    # Headers that claim more pixels than any HDRI (a MemoryError before), or than the file holds
    ("huge.hdr", b"#?RADIANCE\n\n-Y 1000000 +X 1000000\n" + bytes(64), "claims 1000000x1000000"),
    ("wide.hdr", b"#?RADIANCE\n\n-Y 16000 +X 32000\n" + bytes(64), "holds only 64 bytes"),
    ("zero.hdr", b"#?RADIANCE\n\n-Y 0 +X 8\n", "size of 8x0"),
    ("exposure.hdr", b"#?RADIANCE\nEXPOSURE=0\n\n-Y 1 +X 2\n" + bytes(8), "EXPOSURE of 0"),
])
def test_bad_files_are_clear_input_errors(tmp_path, name, content, match):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=match):
        hdri_io.read_hdri(path)


def test_exr_whose_header_claims_a_huge_image_is_refused_before_reading(tmp_path):
    path = _write_exr(tmp_path / "a.exr", _image(4, 8))
    data = bytearray(path.read_bytes())
    at = data.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    data[at + 8:at + 16] = np.array([99999, 49999], "<i4").tobytes()  # xMax, yMax
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="claims 100000x50000 pixels"):
        hdri_io.read_hdri(path)


def test_exr_without_colour_channels(tmp_path):
    header = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Z": np.zeros((4, 8), np.float32)}) as f:
        f.write(str(tmp_path / "depth.exr"))
    with pytest.raises(InputError, match="no R, G, B"):
        hdri_io.read_hdri(tmp_path / "depth.exr")


def test_shared_blender_hdri(shared_data):
    img = hdri_io.read_hdri(shared_data / "hdri" / "blender" / "studio.exr")
    assert img.shape == (512, 1024, 3) and np.isfinite(img).all()
    assert img.max() > 10 * np.median(img) > 0  # a studio map: bright softboxes on a dim ground


def _blender_studio_hdris():
    """Blender's bundled studio HDRIs, from the bpy wheel's data files (bpy is not imported)."""
    import importlib.util
    import pathlib

    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        return []
    return sorted(pathlib.Path(spec.origin).parent.glob("*/datafiles/studiolights/world/*.exr"))


def test_a_file_s_rounding_below_zero_is_not_damage():
    """Negative texels within hdri.ROUNDING of the mean radiance are the file's compression
    rounding (no warning); NaN, infinite and deeper negative texels are counted."""
    img = np.ones((8, 16, 3), np.float32)
    img[0, 0, 0] = -0.5 * hdri.ROUNDING
    assert hdri.damaged_texels(img) == 0
    img[1, 1, 1], img[2, 2, 2], img[3, 3, 0] = -0.3, np.nan, np.inf
    assert hdri.damaged_texels(img) == 3
    assert hdri.damaged_texels(np.zeros((8, 16, 3), np.float32)) == 0
    # either way the repaired map has no negative texel
    assert hdri.check_equirect(img, repair=True).min() == 0.0


def test_blender_s_own_studio_hdris_are_not_damaged():
    """Each of Blender's studio HDRIs but one holds a few tiny negative values; relighting with
    them must not warn the artist about their file."""
    files = _blender_studio_hdris()
    if not files:
        pytest.skip("the bpy wheel's studio HDRIs were not found")
    negative = 0
    for path in files:
        img = hdri_io.read_hdri(path)
        negative += int((img < 0).sum())
        assert hdri.damaged_texels(img) == 0, path.name
    assert negative > 0  # the check has something to pass over
