"""The simulated camera (training/intrinsic/camera.py): sRGB formulas, the output contract,
reproducibility, strength 0, auto exposure, black frames, JPEG, greyscale, odd sizes."""

import math

import pytest
import torch

from training.intrinsic import camera

torch.set_num_threads(1)


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def lum(img):
    return camera.luminance(img).flatten(1)


def smooth_image(n=2, h=64, w=64):
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = 0.2 + 0.5 * xx + 0.2 * torch.sin(3 * yy)
    img = torch.stack([base, 0.9 * base, 0.7 * base + 0.1])[None]
    return img.expand(n, -1, -1, -1).clone()


def scene(n=8, h=48, w=40, seed=1):
    """Random linear scenes: coloured blobs at exposures over six decades."""
    g = gen(seed)
    low = torch.rand(n, 3, 6, 5, generator=g) ** 2
    img = torch.nn.functional.interpolate(low, size=(h, w), mode="bilinear", align_corners=False)
    return img * torch.exp(torch.empty(n, 1, 1, 1).uniform_(-7, 7, generator=g))


# ---- sRGB

def test_srgb_encode_decode_are_inverse_and_standard():
    x = torch.linspace(0, 1, 100001)
    assert float((camera.srgb_decode(camera.srgb_encode(x)) - x).abs().max()) < 1e-5
    assert float((camera.srgb_encode(camera.srgb_decode(x)) - x).abs().max()) < 1e-5
    # Reference values of the piecewise formula: the knee, mid grey and white.
    assert float(camera.srgb_encode(torch.tensor(0.0031308))) == pytest.approx(0.04045, abs=1e-6)
    assert float(camera.srgb_encode(torch.tensor(0.18))) == pytest.approx(
        1.055 * 0.18 ** (1 / 2.4) - 0.055, abs=1e-6)
    assert float(camera.srgb_encode(torch.tensor(1.0))) == pytest.approx(1.0, abs=1e-6)
    assert float(camera.srgb_decode(torch.tensor(0.02))) == pytest.approx(0.02 / 12.92, rel=1e-6)
    assert float(camera.srgb_encode(torch.tensor(-1.0))) == 0.0


def test_curve_lookup_is_within_a_twentieth_of_a_code_value():
    # The pipeline encodes through a per-image table indexed by sqrt(x); check the stated accuracy.
    x = torch.linspace(0, 1, 200001).view(1, 1, 1, -1)
    table = camera.srgb_encode(camera.LUT_GRID ** 2)[None]
    err = (camera._lookup(x, table) - camera.srgb_encode(x)).abs().max()
    assert float(err) * 255 < 0.06


# ---- the pipeline's contract

def test_output_is_finite_non_negative_float32_and_shaped():
    img = scene(16)
    for seed in range(3):
        out = camera.camera_pipeline(img, gen(seed), 1.0)
        assert out.shape == img.shape and out.dtype == torch.float32
        assert bool(torch.isfinite(out).all())
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    before = img.clone()
    camera.camera_pipeline(img, gen(0))
    assert torch.equal(img, before)  # the input batch is left alone


def test_reproducible_with_the_same_seed_only():
    img = scene(8)
    a = camera.camera_pipeline(img, gen(5), 1.0)
    b = camera.camera_pipeline(img, gen(5), 1.0)
    c = camera.camera_pipeline(img, gen(6), 1.0)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_strength_changes_the_picture():
    img = scene(16)
    plain = camera.camera_pipeline(img, gen(3), 0.0)
    full = camera.camera_pipeline(img, gen(3), 1.0)
    assert float((plain - full).abs().mean()) > 1e-3


def test_strength_zero_keeps_a_grey_ramp_ordered_and_grey():
    ramp = torch.linspace(0, 1, 256) ** 2
    img = ramp.view(1, 1, 1, -1).expand(4, 3, 8, -1).contiguous()
    for seed in range(4):
        out = camera.camera_pipeline(img, gen(seed), 0.0)
        assert torch.equal(out[:, 0], out[:, 1]) and torch.equal(out[:, 1], out[:, 2])
        assert bool((out.diff(dim=-1) >= 0).all())  # 8 bits may tie neighbours, never swap them
        assert bool((out[..., -1] > out[..., 0]).all())
        # Exposure alone: the same ramp at any scale gives the same picture (up to a code value).
        for scale in (1e-3, 1e4):
            assert torch.allclose(camera.camera_pipeline(img * scale, gen(seed), 0.0), out, atol=0.01)


@pytest.mark.parametrize("size", [(48, 40), (128, 128)])  # every pixel; a 2x2 grid of them
def test_auto_exposure_puts_the_quantile_in_range(size):
    base = scene(32, *size, seed=2)
    img = base.mean(1, keepdim=True) * (0.9 + 0.2 * base / base.amax((1, 2, 3), keepdim=True))
    out = camera.camera_pipeline(img, gen(4), 0.0)
    q = torch.quantile(lum(out), 0.9, dim=1)
    tol = 0.01  # 8-bit codes near white are ~0.009 apart in linear
    assert float(q.min()) >= camera.EXPOSURE_RANGE[0] - tol
    assert float(q.max()) <= camera.EXPOSURE_RANGE[1] + tol
    assert float(q.max() - q.min()) > 0.15  # the level is drawn, not fixed


def test_a_black_frame_stays_black():
    img = scene(6)
    img[2] = 0.0
    for seed in range(4):
        out = camera.camera_pipeline(img, gen(seed), 1.0)
        assert bool(torch.isfinite(out).all())
        assert float(out[2].abs().max()) == 0.0
        assert float(out[3].max()) > 0.0
    out = camera.camera_pipeline(torch.zeros(3, 3, 16, 16), gen(0), 1.0)
    assert bool(torch.isfinite(out).all()) and float(out.abs().max()) == 0.0


def test_a_small_subject_on_black_is_not_blown_out():
    img = torch.zeros(1, 3, 64, 64)
    img[..., 28:36, 28:36] = 0.5  # 1.6% of the frame: the 0.9 quantile is black
    out = camera.camera_pipeline(img, gen(0), 0.0)
    assert 0.0 < float(out[..., 30:34, 30:34].mean()) <= 1.0
    assert float(out[..., :20, :20].max()) == 0.0


def test_odd_and_tiny_sizes_work():
    for h, w in ((37, 53), (3, 5), (9, 17)):
        img = scene(12, h, w, seed=h)
        for seed in range(3):
            out = camera.camera_pipeline(img, gen(seed), 1.0)
            assert out.shape == (12, 3, h, w)
            assert bool(torch.isfinite(out).all()) and float(out.min()) >= 0.0


def test_full_strength_draws_every_stage():
    # With 64 draws every branch fires; white balance gives grey pictures colour casts.
    img = smooth_image(64, 24, 24).mean(1, keepdim=True).expand(-1, 3, -1, -1)
    out = camera.camera_pipeline(img, gen(1), 1.0)
    cast = (out[:, 0] - out[:, 2]).abs().mean((1, 2))
    assert int((cast > 0.01).sum()) > 10


# ---- stages

def test_jpeg_is_gentle_at_high_quality_and_harsh_at_low():
    smooth = camera.srgb_encode(smooth_image())
    for sub in (False, True):
        assert float((camera.jpeg_compress(smooth, 95.0, sub) - smooth).abs().mean()) < 0.01
    noisy = torch.rand(2, 3, 37, 53, generator=gen(0))
    err95 = (camera.jpeg_compress(noisy, 95.0) - noisy).abs().mean()
    err40 = (camera.jpeg_compress(noisy, 40.0) - noisy).abs().mean()
    assert float(err40) > 2 * float(err95) > 0
    assert camera.jpeg_compress(noisy, torch.tensor([40.0, 95.0]), True).shape == noisy.shape


def test_jpeg_keeps_flat_mid_grey_exactly():
    # Y = 128 and Cb = Cr = 0 after the level shift: all coefficients zero at any quality.
    grey = torch.full((2, 3, 16, 24), 128 / 255)
    for q in (40.0, 70.0, 95.0):
        for sub in (False, True):
            assert float((camera.jpeg_compress(grey, q, sub) - grey).abs().max()) < 1e-5


def test_jpeg_matches_a_block_by_block_reference():
    x = torch.rand(2, 3, 16, 24, generator=gen(3))
    luma_t, chroma_t = camera.jpeg_tables(torch.tensor([50.0, 80.0]))
    ycc = torch.einsum("ij,njhw->nihw", camera.YCC, x) * 255
    ycc[:, 0] -= 128  # level shift; chroma's +128 offset and -128 shift cancel
    d = camera.DCT
    out = torch.empty_like(ycc)
    for n in range(2):
        for c in range(3):
            t = (luma_t if c == 0 else chroma_t)[n].view(8, 8)
            for i in range(0, 16, 8):
                for j in range(0, 24, 8):
                    coef = d @ ycc[n, c, i:i + 8, j:j + 8] @ d.T
                    out[n, c, i:i + 8, j:j + 8] = d.T @ (torch.round(coef / t) * t) @ d
    out[:, 0] += 128
    ref = torch.einsum("ij,njhw->nihw", camera.YCC_INV, out / 255)
    assert float((camera.jpeg_compress(x, torch.tensor([50.0, 80.0])) - ref).abs().max()) < 1e-4


def test_jpeg_tables_follow_libjpeg_scaling():
    luma, chroma = camera.jpeg_tables(torch.tensor([50.0, 100.0, 25.0]))
    assert torch.equal(luma[0], camera.JPEG_LUMA.flatten())
    assert float(luma[1].max()) == 1.0
    assert float(chroma[2, 0]) == math.floor((17 * 200 + 50) / 100)


def test_tone_curve_is_the_stated_s_curve():
    x = torch.linspace(0, 1, 1001).expand(3, -1)
    a, p = torch.tensor([1.0, 1.6, 0.7]), torch.tensor([0.3, 0.2, 0.45])
    y = camera.tone_curve(x, a, p)
    assert torch.allclose(y[0], x[0], atol=1e-6)
    c = (p / (1 - p)) ** (a - 1)
    closed = x ** a[:, None] / (x ** a[:, None] + c[:, None] * (1 - x) ** a[:, None])
    assert torch.allclose(y, closed, atol=1e-5)
    assert bool((y.diff(dim=1) >= 0).all()) and float(y[:, 0].max()) == 0.0
    assert torch.allclose(y[:, -1], torch.ones(3))
    assert torch.allclose(camera.tone_curve(p[:, None], a, p)[:, 0], p, atol=1e-6)


def test_blur_preserves_flat_images_and_spreads_a_point():
    flat = torch.full((2, 3, 11, 13), 0.4)
    assert torch.allclose(camera.gaussian_blur(flat, torch.tensor([0.3, 1.2])), flat, atol=1e-6)
    dot = torch.zeros(2, 1, 21, 21)
    dot[..., 10, 10] = 1.0
    out = camera.gaussian_blur(dot, torch.tensor([0.5, 1.2]))
    assert torch.allclose(out.sum((1, 2, 3)), torch.ones(2), atol=1e-5)
    assert float(out[0, 0, 10, 10]) > float(out[1, 0, 10, 10])  # wider sigma, lower peak


def test_noise_has_the_stated_level():
    v = torch.full((1, 3, 128, 128), 0.5)
    out = camera._noise(v, torch.tensor([0.004]), torch.tensor([0.01]), gen(0))
    assert float(out.std()) == pytest.approx(math.sqrt(0.004 * 0.5 + 0.01 ** 2), rel=0.05)


# ---- greyscale

def test_greyscale_makes_chosen_images_grey_and_leaves_the_rest():
    img = scene(64)
    out = camera.greyscale(img, gen(0), 0.5)
    grey = (out[:, 0] == out[:, 1]).all((1, 2)) & (out[:, 1] == out[:, 2]).all((1, 2))
    assert 10 < int(grey.sum()) < 54
    assert torch.allclose(out[grey, 0], camera.luminance(img[grey]))
    assert torch.equal(out[~grey], img[~grey])
    assert torch.equal(camera.greyscale(img, gen(0), 0.0), img)
    every = camera.greyscale(img, gen(1), 1.0)
    assert torch.equal(every[:, 0], every[:, 1]) and torch.equal(every[:, 1], every[:, 2])
    assert torch.equal(out, camera.greyscale(img, gen(0), 0.5))
