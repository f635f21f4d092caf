"""Pins the light-vector convention of design.md: cell centres, orientation, solid angles."""

import math

import numpy as np
import pytest

from addon import hdri, lightvec
from addon.errors import InputError, LightingError


def test_solid_angles_sum_to_sphere():
    assert lightvec.solid_angles().shape == (16, 16)
    assert lightvec.solid_angles().sum() == pytest.approx(4 * math.pi, rel=1e-12)


def test_cell_centres_follow_design():
    d = lightvec.directions()
    # Column 8 faces the camera (+Z); rows 7 and 8 straddle the equator.
    assert d[7, 8] == pytest.approx([0, math.cos(7.5 * math.pi / 16), math.sin(7.5 * math.pi / 16)])
    # Column 12 is azimuth +90 degrees: the camera's right (+X).
    assert d[8, 12][0] > 0.99
    # Column 4 is the camera's left, column 0 straight behind.
    assert d[8, 4][0] < -0.99 and d[8, 0][2] < -0.99
    # Row 0 is near the zenith, row 15 near the nadir.
    assert d[0, 0][1] > 0.98 and d[15, 0][1] < -0.98
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)


def test_directions_map_back_to_their_cells():
    row, col = lightvec.directions_to_cells(lightvec.directions())
    np.testing.assert_array_equal(row, np.arange(16)[:, None].repeat(16, 1))
    np.testing.assert_array_equal(col, np.arange(16)[None, :].repeat(16, 0))


def test_uniform_environment_gives_pi_irradiance():
    e = lightvec.irradiance(lightvec.uniform(1.0), np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0]]))
    # Exact value is pi; the 16x16 midpoint quadrature of the clamped cosine is within 2% (it
    # measures 1.5% low for a normal at 45 deg between columns): inherent to the representation.
    np.testing.assert_allclose(e, math.pi, rtol=0.02)


def test_light_to_the_camera_right_lights_right_texels():
    light = lightvec.splat_direction([1.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    right = light[:, 9:16].sum()
    left = light[:, 1:8].sum()
    assert right > 0 and left == 0
    # And a normal facing right receives its irradiance, a left-facing one nothing.
    e = lightvec.irradiance(light, np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert e[0] == pytest.approx([1, 1, 1], rel=0.03) and np.all(e[1] == 0)


@pytest.mark.parametrize("direction", [[0.3, 0.5, 0.8], [0, 1, 0], [0, -1, 0], [-0.2, 0.1, -1]])
def test_splat_conserves_irradiance(direction):
    light = lightvec.splat_direction(direction, [2.0, 1.0, 0.5])
    np.testing.assert_allclose(lightvec.total_power(light), [2.0, 1.0, 0.5], rtol=1e-6)


def test_rotate_360_is_identity_and_conserves_rows():
    rng = np.random.default_rng(0)
    light = rng.random((16, 16, 3)).astype(np.float32)
    np.testing.assert_allclose(lightvec.rotate_azimuth(light, 360.0), light, atol=1e-6)
    r = lightvec.rotate_azimuth(light, 37.0)
    np.testing.assert_allclose(r.sum(axis=1), light.sum(axis=1), rtol=1e-5)
    # 22.5 degrees moves everything one column toward +X.
    np.testing.assert_allclose(lightvec.rotate_azimuth(light, 22.5), np.roll(light, 1, axis=1))


def test_validate_rejects_bad_vectors():
    with pytest.raises(LightingError, match="shape"):
        lightvec.validate(np.zeros((8, 8, 3)))
    bad = lightvec.zeros()
    bad[3, 3, 1] = np.nan
    with pytest.raises(LightingError, match="NaN"):
        lightvec.validate(bad)
    bad[3, 3, 1] = -1
    with pytest.raises(LightingError, match="negative"):
        lightvec.validate(bad)


def test_hdri_uniform_is_all_ones_under_any_rotation():
    img = np.ones((64, 128, 3), np.float32)
    rot = hdri.world_to_frame_from_camera(hdri.yaw_world(33.0) @ _rot_x(70.0))
    out = hdri.downsample(img, rot, yaw_degrees=12.0)
    np.testing.assert_allclose(out, 1.0, rtol=1e-6)


@pytest.mark.parametrize("size", [(32, 64), (256, 512), (512, 1024)])
def test_hdri_downsampling_conserves_energy(size):
    h, w = size
    rng = np.random.default_rng(1)
    img = rng.gamma(0.5, 2.0, (h, w, 3)).astype(np.float32)
    img[h // 3, w // 5] = 1e5  # a sun
    omega = hdri.pixel_row_solid_angles(h, w)
    truth = (img.astype(np.float64) * omega[:, None, None]).sum(axis=(0, 1))
    out = hdri.downsample(img, yaw_degrees=17.0)
    np.testing.assert_allclose(lightvec.total_power(out), truth, rtol=0.01)


def test_hdri_orientation_image_centre_faces_world_x():
    # A bright patch at the image centre (u=0.5, on the horizon) is world +X: in the front view
    # (camera on -Y looking at +Y) that is the camera's right.
    img = np.zeros((128, 256, 3), np.float32)
    img[60:68, 124:132] = 1.0
    out = hdri.downsample(img)
    assert out[:, 12].sum() > 0.9 * out.sum()
    # Top rows of the image are the zenith.
    img = np.zeros((128, 256, 3), np.float32)
    img[:4] = 1.0
    assert hdri.downsample(img)[0].sum() > 0.99 * hdri.downsample(img).sum()


def test_hdri_gives_the_same_light_vector_on_every_call():
    """A map whose pixel centres lie on the cells' edges in the front view (40 columns, enlarged
    to 1040: 16 x 65) bins each pixel into one cell whatever the arrays' places in memory (the
    last bit of numpy's vectorised trigonometry follows them): two processes of one farm run
    agree on the lighting, and the light vector stays linear in the map."""
    img = (10.0 ** np.random.default_rng(3).uniform(-6, 3, (20, 40, 3))).astype(np.float32)
    junk = []
    outs = []
    for k in range(6):
        junk.append(np.empty(1 + 977 * k, np.uint8))  # another heap layout for each call
        outs.append(hdri.downsample(img))
    for out in outs[1:]:
        np.testing.assert_array_equal(out, outs[0])
    np.testing.assert_allclose(hdri.downsample(img * np.float32(92.5)), outs[0] * 92.5, rtol=1e-5)


def test_hdri_bad_input_messages():
    with pytest.raises(InputError, match="twice as wide"):
        hdri.downsample(np.ones((100, 100, 3), np.float32))
    img = np.ones((64, 128, 3), np.float32)
    img[0, 0, 0] = np.nan
    img[1, 1, 1] = -2
    with pytest.raises(LightingError, match="1 NaN, 0 infinite and 1 negative"):
        hdri.downsample(img)
    assert np.isfinite(hdri.downsample(img, repair=True)).all()
    ok = np.ones((64, 128, 3), np.float32)
    for kw in (dict(yaw_degrees=float("nan")), dict(yaw_degrees=float("inf")),
               dict(world_to_frame=np.full((3, 3), np.nan))):
        with pytest.raises(LightingError, match="rotation"):
            hdri.downsample(ok, **kw)
    with pytest.raises(LightingError, match="strength is nan"):
        hdri.downsample(ok, strength=float("nan"))


def _rot_x(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
