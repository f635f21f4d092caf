"""A simulated camera for training inputs: closes the gap between rendered and filmed pixels.

The light stage renders scene-linear Rec.709 radiance at arbitrary exposure. Real footage has been
through a camera (exposure, white balance, a tone curve, sRGB encoding, blur or sharpening, sensor
noise, JPEG/H.264 compression, 8-bit quantisation) and the product decodes it back to linear with
the plain sRGB EOTF. ``camera_pipeline`` simulates both halves on a batch, so the network sees the
same kind of decoded-linear image at training time as in use. Torch only; every random draw comes
from the caller's generator, so a batch is reproducible from a seed.

``strength`` in [0, 1] scales how far the camera strays from identity: continuous parameters
(white balance, tone-curve contrast, noise levels) scale in magnitude, discrete events (blur,
sharpening, compression) in probability. Strength 0 keeps auto exposure, sRGB and 8 bits only.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

LUMA = (0.2126, 0.7152, 0.0722)  # Rec.709, as the product's exposure normalisation
EXPOSURE_QUANTILE = 0.9
EXPOSURE_RANGE = (0.35, 0.85)  # linear level of the 0.9 luminance quantile, log-uniform
WB_SD, TINT_SD, TINT_P = 0.08, 0.2, 0.2
TONE_P = 0.5
TONE_LOG_A = (-0.35, 0.5)  # log contrast exponent: a in [0.70, 1.65] at strength 1, 1 is identity
TONE_PIVOT = (0.18, 0.45)  # linear level the curve leaves in place, log-uniform
BLUR_P, BLUR_SIGMA = 0.3, (0.3, 1.2)
SHARPEN_P, SHARPEN_AMOUNT, SHARPEN_SIGMA = 0.3, (0.2, 0.8), (0.5, 1.2)
LUT_SIZE = 4096  # tone curve + sRGB encode table, indexed by sqrt(linear)
LUT_GRID = torch.linspace(0, 1, LUT_SIZE)
RADIUS = 4  # ceil(3 * the largest sigma)
NOISE_P, NOISE_A, NOISE_B = 0.7, 0.004, 0.01
JPEG_P, JPEG_QUALITY, SUBSAMPLE_P = 0.5, (40.0, 95.0), 0.5

JPEG_LUMA = torch.tensor([
    [16, 11, 10, 16, 24, 40, 51, 61], [12, 12, 14, 19, 26, 58, 60, 55],
    [14, 13, 16, 24, 40, 57, 69, 56], [14, 17, 22, 29, 51, 87, 80, 62],
    [18, 22, 37, 56, 68, 109, 103, 77], [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101], [72, 92, 95, 98, 112, 100, 103, 99]], dtype=torch.float32)
JPEG_CHROMA = torch.full((8, 8), 99.0)
JPEG_CHROMA[:4, :4] = torch.tensor([
    [17, 18, 24, 47], [18, 21, 26, 66], [24, 26, 56, 99], [47, 66, 99, 99]], dtype=torch.float32)

# Orthonormal DCT-II: equals JPEG's FDCT normalisation, so the standard tables apply unchanged.
_k = torch.arange(8, dtype=torch.float64)
DCT = torch.cos((2 * _k[None, :] + 1) * _k[:, None] * math.pi / 16) * math.sqrt(2 / 8)
DCT[0] /= math.sqrt(2)
DCT = DCT.float()
# JFIF full-range YCbCr (offsets applied separately); the inverse is exact, not the rounded one.
_YCC = torch.tensor([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]],
                    dtype=torch.float64)
YCC = _YCC.float()
YCC_INV = torch.linalg.inv(_YCC).float()


# Powers as exp(log): twice as fast as torch.pow on the CPU, and these run on every training pixel.

def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """Linear -> sRGB (the IEC 61966-2-1 piecewise OETF); negatives map to 0."""
    x = x.clamp(min=0)
    power = x.clamp(min=0.0031308).log_().mul_(1 / 2.4).exp_().mul_(1.055).sub_(0.055)
    return torch.where(x > 0.0031308, power, x * 12.92)


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    """sRGB -> linear (the piecewise EOTF the product applies to footage); negatives map to 0."""
    x = x.clamp(min=0)
    power = x.clamp(min=0.04045).add_(0.055).mul_(1 / 1.055).log_().mul_(2.4).exp_()
    return torch.where(x > 0.04045, power, x * (1 / 12.92))


# 8-bit code value -> linear: quantisation and the product's decode in one gather.
DECODE_8BIT = srgb_decode(torch.arange(256, dtype=torch.float32) / 255)


def luminance(img: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, H, W) Rec.709 luminance."""
    w = torch.tensor(LUMA, dtype=img.dtype, device=img.device)
    b, _, h, wd = img.shape
    return (w @ img.reshape(b, 3, h * wd)).view(b, h, wd)  # a product: 5x faster than einsum


def greyscale(img: torch.Tensor, gen: torch.Generator, p: float) -> torch.Tensor:
    """With probability p per image, its luminance in all three channels (as grey data is fed)."""
    pick = _rand(gen, (img.shape[0],), img.device) < p
    idx = torch.nonzero(pick).squeeze(1)
    out = img.clone()
    out[idx] = luminance(img[idx])[:, None].expand(-1, img.shape[1], -1, -1)
    return out


def _rand(gen: torch.Generator, shape, device) -> torch.Tensor:
    # Draw on the generator's device, then move: works for a CPU generator with a GPU batch.
    return torch.rand(shape, generator=gen, device=gen.device).to(device)


def _randn(gen: torch.Generator, shape, device) -> torch.Tensor:
    return torch.randn(shape, generator=gen, device=gen.device).to(device)


def _between(u: torch.Tensor, lo: float, hi: float, log: bool = False) -> torch.Tensor:
    if log:
        return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
    return lo + u * (hi - lo)


def _pad(x: torch.Tensor, pads: tuple[int, int, int, int]) -> torch.Tensor:
    # Reflection needs pad < size; tiny images fall back to edge replication.
    h, w = x.shape[-2:]
    mode = "reflect" if max(pads[:2]) < w and max(pads[2:]) < h else "replicate"
    return F.pad(x, pads, mode=mode)


def gaussian_blur(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian blur of (n, C, H, W) with one sigma (pixels) per image, reflect padding."""
    n, c, h, w = x.shape
    t = torch.arange(-RADIUS, RADIUS + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t[None] / sigma[:, None].clamp(min=1e-3)) ** 2)
    k = (k / k.sum(1, keepdim=True)).repeat_interleave(c, 0)  # (n*c, K)
    y = x.reshape(1, n * c, h, w)
    y = F.conv2d(_pad(y, (RADIUS, RADIUS, 0, 0)), k[:, None, None, :], groups=n * c)
    y = F.conv2d(_pad(y, (0, 0, RADIUS, RADIUS)), k[:, None, :, None], groups=n * c)
    return y.reshape(n, c, h, w)


def jpeg_tables(quality: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image (n, 64) luma and chroma tables (row-major 8x8) at IJG quality 1..100, scaled as
    libjpeg scales them."""
    q = quality.clamp(1, 100).round()
    scale = torch.where(q < 50, 5000 / q, 200 - 2 * q).view(-1, 1)
    luma = torch.floor((JPEG_LUMA.flatten().to(q.device) * scale + 50) / 100).clamp(1, 255)
    chroma = torch.floor((JPEG_CHROMA.flatten().to(q.device) * scale + 50) / 100).clamp(1, 255)
    return luma, chroma


def _block_quantise(plane: torch.Tensor, table: torch.Tensor, dc_shift: list[float]) -> torch.Tensor:
    """Quantise the 8x8 block DCT of (n, c, H, W) planes (0..255 units, H and W multiples of 8)
    with row-major tables (n, c, 64). The DCT runs separably on the image layout (D X D^T: rows
    within blocks, then columns), so no block gathering copies are needed. dc_shift: per plane,
    JPEG's level shift, applied to the DC term (an orthonormal 8x8 DCT's DC is 8 x the block mean)."""
    n, c, h, w = plane.shape
    d = DCT.to(plane.device, plane.dtype)
    coef = (d @ plane.reshape(n, c, h // 8, 8, w)).view(n, c, h, w // 8, 8) @ d.T
    blocks = coef.view(n, c, h // 8, 8, w // 8, 8)  # (.., block row, u, block col, v)
    table = table.view(n, c, 1, 8, 1, 8)
    shift = torch.tensor(dc_shift, dtype=plane.dtype, device=plane.device).view(1, c, 1, 1) * 8
    blocks[:, :, :, 0, :, 0] -= shift
    blocks.mul_(1 / table).round_().mul_(table)
    blocks[:, :, :, 0, :, 0] += shift
    return ((d.T @ coef.view(n, c, h // 8, 8, w)).view(n, c, h, w // 8, 8) @ d).view(n, c, h, w)


def jpeg_compress(x: torch.Tensor, quality, subsample: bool = False) -> torch.Tensor:
    """JPEG-like round trip of sRGB-encoded (n, 3, H, W) in [0, 1]: YCbCr, 8x8 block DCT, the
    standard tables at ``quality`` (a number or one per image), optional 2x chroma subsampling.
    Any size: padded by reflection to whole blocks and cropped back."""
    n, _, h, w = x.shape
    quality = torch.as_tensor(quality, dtype=torch.float32, device=x.device).expand(n)
    luma_t, chroma_t = jpeg_tables(quality)
    block = 16 if subsample else 8  # subsampled chroma must still fill whole 8x8 blocks
    x = _pad(x, (0, -w % block, 0, -h % block))
    # Chroma's +128 offset and the DCT's -128 level shift cancel: only luma needs the shift.
    ycc = torch.einsum("ij,njhw->nihw", YCC.to(x.device) * 255, x)
    if subsample:
        y = _block_quantise(ycc[:, :1], luma_t[:, None], [128.0])
        chroma_t = chroma_t[:, None].expand(-1, 2, -1)
        chroma = _block_quantise(F.avg_pool2d(ycc[:, 1:], 2), chroma_t, [0.0, 0.0])
        chroma = F.interpolate(chroma, size=ycc.shape[-2:], mode="bilinear", align_corners=False)
        ycc = torch.cat([y, chroma], 1)
    else:
        ycc = _block_quantise(ycc, torch.stack([luma_t, chroma_t, chroma_t], 1), [128.0, 0.0, 0.0])
    rgb = torch.einsum("ij,njhw->nihw", YCC_INV.to(x.device) / 255, ycc)
    return rgb[..., :h, :w]


def tone_curve(x: torch.Tensor, a: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
    """Smooth monotone S-curve on [0, 1]: x^a / (x^a + c (1-x)^a) with c = (p / (1-p))^(a-1), so
    the pivot p stays put; a > 1 adds contrast, a < 1 flattens, a = 1 is the identity. Computed as
    a contrast in logit space, sigmoid(a (logit x - logit p) + logit p): same curve, fewer powers
    (0 and 1 go through +-inf to exactly 0 and 1). a and pivot: one per image."""
    shape = (-1,) + (1,) * (x.dim() - 1)  # one value per image, whatever x's trailing dims
    a, lp = a.view(shape), torch.logit(pivot).view(shape)
    return torch.logit(x.clamp(0, 1)).sub_(lp).mul_(a).add_(lp).sigmoid_()


def _lookup(x: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Per-image curve lookup: x (B, C, H, W) in [0, 1], table (B, LUT_SIZE) sampled at
    x = LUT_GRID ** 2. Indexing by sqrt(x) spends the entries where the sRGB curve is steep (near
    black): nearest entry is then within 0.05 of an 8-bit code value of the exact curve, and over
    twice as fast as evaluating the powers per pixel. int32 indices into the flattened tables:
    converting to int64 costs more than the lookup itself."""
    b, size = table.shape
    start = torch.arange(b, device=x.device, dtype=torch.int32).mul_(size).view(-1, 1, 1, 1)
    idx = x.sqrt().mul_(size - 1).add_(0.5).to(torch.int32).add_(start)  # + 0.5, truncate: nearest
    return table.reshape(-1).index_select(0, idx.view(-1)).view_as(x)


def _apply(x: torch.Tensor, mask: torch.Tensor, fn) -> None:
    """x[mask] = fn(x[mask], indices), in place: blur, noise and JPEG cost time only on the
    images that draw them."""
    idx = torch.nonzero(mask).squeeze(1)
    if idx.numel():
        x.index_copy_(0, idx, fn(x[idx], idx))


def _sharpen(v: torch.Tensor, sigma: torch.Tensor, amount: torch.Tensor) -> torch.Tensor:
    """Unsharp mask v + amount (v - blur(v)), clipped as a camera's output is. amount -1 is a
    plain blur, so blurred and sharpened images share one call."""
    amount = amount.view(-1, 1, 1, 1)
    return gaussian_blur(v, sigma).mul_(-amount).add_(v * (1 + amount)).clamp_(0, 1)


def _noise(v: torch.Tensor, a: torch.Tensor, b: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Shot plus read noise, sd = sqrt(a x + b^2), on encoded values, clipped."""
    sd = (v * a.view(-1, 1, 1, 1)).add_(b.view(-1, 1, 1, 1) ** 2).sqrt_()
    return _randn(gen, v.shape, v.device).mul_(sd).add_(v).clamp_(0, 1)


@torch.no_grad()
def camera_pipeline(img: torch.Tensor, gen: torch.Generator, strength: float = 1.0) -> torch.Tensor:
    """Simulated camera plus the product's sRGB decode, per image of a (B, 3, H, W) linear batch
    (finite, >= 0, any scale). Returns a new float32 (B, 3, H, W) batch of linear values in
    [0, 1]. All-zero images stay zero (a black frame has no exposure to set, nothing to learn)."""
    s = float(min(max(strength, 0.0), 1.0))
    x = img.float()
    b, dev = x.shape[0], x.device
    # Every per-image draw up front in one fixed layout, so the seed alone fixes the batch.
    u = _rand(gen, (b, 16), dev)
    z = _randn(gen, (b, 2), dev)

    # 1. Auto exposure on the 0.9 luminance quantile. The reference never drops below 1e-3 of the
    # peak, so a small subject on black is not blown out to white. The quantile is the nearest
    # rank (kthvalue: ~5x faster than torch.quantile) over a pixel grid of about 4096 or more
    # (every pixel up to 95x95, every 2nd at 128x128): the level is random anyway.
    full = luminance(x)
    peak = full.view(b, -1).amax(1)
    step = max(1, round(math.sqrt(full[0].numel() / 4096)))
    lum = full[:, ::step, ::step].reshape(b, -1)
    rank = round(EXPOSURE_QUANTILE * (lum.shape[1] - 1)) + 1
    ref = torch.maximum(lum.kthvalue(rank, dim=1).values, 1e-3 * peak)
    black = peak <= 0
    level = _between(u[:, 0], *EXPOSURE_RANGE, log=True)
    exposure = torch.where(black, 0.0, level / ref.clamp(min=1e-30))

    # 2. White balance error: R and B gains relative to G, occasionally a strong tint. One
    # multiply with the exposure; highlights then clip as they do in the sensor.
    sd = torch.where(u[:, 1] < TINT_P * s, TINT_SD * s, WB_SD * s)
    gains = torch.stack([torch.exp(z[:, 0] * sd), torch.ones_like(sd), torch.exp(z[:, 1] * sd)], 1)
    x = (x * (gains * exposure[:, None]).view(-1, 3, 1, 1)).clamp_(0, 1)

    # 3. Tone curve, its contrast range shrinking to identity with strength, and 4. sRGB encode:
    # both per-pixel functions of one value, so one lookup in a per-image table does both.
    a = torch.exp(s * _between(u[:, 3], *TONE_LOG_A))
    a = torch.where(u[:, 2] < TONE_P, a, 1.0)
    pivot = _between(u[:, 4], *TONE_PIVOT, log=True)
    x = _lookup(x, srgb_encode(tone_curve((LUT_GRID.to(dev) ** 2).expand(b, -1), a, pivot)))

    # 5. Blur or sharpen (exclusive).
    blur = u[:, 5] < BLUR_P * s
    sharpen = (u[:, 5] >= BLUR_P * s) & (u[:, 5] < (BLUR_P + SHARPEN_P) * s)
    sigma = torch.where(blur, _between(u[:, 6], *BLUR_SIGMA), _between(u[:, 6], *SHARPEN_SIGMA))
    amount = torch.where(blur, -1.0, _between(u[:, 7], *SHARPEN_AMOUNT))
    _apply(x, blur | sharpen, lambda v, i: _sharpen(v, sigma[i], amount[i]))

    # 6. Signal-dependent sensor noise (shot + read); levels shrink to zero with strength.
    na = _between(u[:, 9], 0, NOISE_A * s)
    nb = _between(u[:, 10], 0, NOISE_B * s)
    _apply(x, (u[:, 8] < NOISE_P) & (nb > 0), lambda v, i: _noise(v, na[i], nb[i], gen))

    # 7. Compression, with and without chroma subsampling (separate calls keep each vectorised).
    jpeg = u[:, 11] < JPEG_P * s
    quality = _between(u[:, 12], *JPEG_QUALITY)
    sub = u[:, 13] < SUBSAMPLE_P
    _apply(x, jpeg & sub, lambda v, i: jpeg_compress(v, quality[i], subsample=True))
    _apply(x, jpeg & ~sub, lambda v, i: jpeg_compress(v, quality[i], subsample=False))

    # 8. 8-bit quantisation (round half up) and 9. the product's decode: one lookup on the codes.
    code = x.clamp_(0, 1).mul_(255).add_(0.5).to(torch.int32)
    x = DECODE_8BIT.to(dev).index_select(0, code.view(-1)).view_as(x)
    if bool(black.any()):
        x[black] = 0.0  # noise would otherwise show on black frames
    return x
