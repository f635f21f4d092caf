"""The relighting network of the paper (sec. 4): an encoder-decoder run per frame.

    L_hat, F, e = encoder(I)                 source light, skip features, structure code
    I_relit, P  = decoder(L, F, e)           L: a target light, or L_hat for self-reconstruction

Built for speed on a CPU (onnxruntime, 2 cores): the image is folded to 1/4 resolution at once
(pixel unshuffle), all convolutions are depthwise-separable inverted residuals, and the full
resolution only sees element-wise work: the relit image is ``gain * image + residual`` where the
gain is a smooth (bilinearly up-sampled) shading ratio and the residual adds light the input lacks.

Units (see addon/normalise.py): the network sees ``image / s``; the decoder sees a light of unit
mean power (``light / k``) and its relit output is in the units of ``image / (s k)``. The source light
is returned in the normalised image's units (``light_i / s``): the light that renders ``image / s``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from addon import contract, lightvec

STEM = 4  # the image is folded to 1/STEM resolution by pixel unshuffle before any convolution
LIGHT_SHAPE = (3, lightvec.ROWS, lightvec.COLS)  # channels-first light vector, as in the contract
LIGHT_SIZE = 3 * lightvec.ROWS * lightvec.COLS
INPUT_CEILING = 1e4  # normalised radiance above this is clipped: keeps fp16/exp paths finite
SOFTPLUS_BETA = 20.0  # irradiance floor softplus(0) = ln 2 / 20 ~ 0.035 (unit lights: E ~ 1)
IRRADIANCE_EPS = 1e-3
RATIO_MAX = 50.0  # a shading ratio above this is clipped (a lit pixel from a near-black one)


@dataclass(frozen=True)
class NetConfig:
    """Width and depth of one preset. ``widths[i]`` is the channel count at stride 4 * 2**i."""

    widths: tuple = (24, 32, 64, 96)
    blocks: tuple = (1, 2, 2, 2)  # residual blocks per encoder level (the decoder uses one fewer)
    expand: int = 2  # inverted-residual expansion factor
    code: int = 64  # channels of the structure code e
    light_embed: int = 64  # width of the light MLP
    classes: int = len(contract.PARSING_CLASSES)
    # "smooth": the residual is a 1/4-resolution map up-sampled bilinearly like the gain, so fine
    # detail can only come from gain * image. "shuffle" (the first Draft's; checkpoints without
    # this key): 4x4 pixel-shuffled residual, which trained into a blurred, gridded image.
    residual: str = "shuffle"
    # "ratio": the gain also carries a per-pixel irradiance ratio E(T, L_target) / E(T, L_source),
    # with a predicted 9-coefficient (order-2 spherical harmonics) transport T per pixel and the
    # encoder's own source estimate, so the light's direction acts on the image through physics
    # rather than only through FiLM (the "gain" decoders learnt colour and level but not direction).
    # "gain" (checkpoints without this key): gain and residual from FiLM features only.
    relight: str = "gain"

    @property
    def stride(self) -> int:
        """Input height and width must be multiples of this (the engine pads)."""
        return STEM * 2 ** (len(self.widths) - 1)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


PRESETS = {
    "draft": NetConfig(widths=(16, 24, 48, 64), blocks=(1, 1, 1, 1), expand=2, code=32,
                       light_embed=48, residual="smooth", relight="ratio"),
    "standard": NetConfig(widths=(32, 48, 96, 128), blocks=(1, 2, 2, 2), expand=2, code=64,
                          light_embed=64, residual="smooth", relight="ratio"),
    # Wide at low resolution, narrow at 1/4: 48 x 3 expanded channels at 1/4 resolution ran 4x
    # slower than this on the 2-core CPU for about the same FLOPs (memory-bound).
    "final": NetConfig(widths=(32, 64, 128, 192), blocks=(1, 3, 4, 3), expand=3, code=128,
                       light_embed=128, residual="smooth", relight="ratio"),
}


def config_for(preset: str, **overrides) -> NetConfig:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    return NetConfig(**{**asdict(PRESETS[preset]), **overrides})


# ----------------------------------------------------------------------------------- building blocks

class InvertedResidual(nn.Module):
    """MobileNetV2 block: 1x1 expand, 3x3 depthwise (optionally strided/dilated), 1x1 project."""

    def __init__(self, cin: int, cout: int, expand: int, stride: int = 1, dilation: int = 1):
        super().__init__()
        mid = cin * expand
        self.residual = stride == 1 and cin == cout
        self.body = nn.Sequential(
            nn.Conv2d(cin, mid, 1), nn.ReLU(inplace=True),
            nn.Conv2d(mid, mid, 3, stride, padding=dilation, dilation=dilation, groups=mid),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid, cout, 1))
        if self.residual:
            # Zero-init the last projection: each residual block starts as the identity, which
            # keeps training stable without normalisation layers (none to fold at export).
            nn.init.zeros_(self.body[-1].weight)
            nn.init.zeros_(self.body[-1].bias)

    def forward(self, x):
        y = self.body(x)
        return x + y if self.residual else y


def _stage(cin: int, cout: int, n: int, expand: int, stride: int) -> nn.Sequential:
    layers = [InvertedResidual(cin, cout, expand, stride)]
    layers += [InvertedResidual(cout, cout, expand) for _ in range(max(n - 1, 0))]
    return nn.Sequential(*layers)


class LightMLP(nn.Module):
    """Light vector -> per-level FiLM scale and shift (the decoder's only view of the light)."""

    def __init__(self, embed: int, level_widths: list[int]):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(LIGHT_SIZE, embed), nn.ReLU(inplace=True),
                                   nn.Linear(embed, embed), nn.ReLU(inplace=True))
        self.heads = nn.ModuleList(nn.Linear(embed, 2 * w) for w in level_widths)
        for h in self.heads:  # start as the identity modulation
            nn.init.zeros_(h.weight)
            nn.init.zeros_(h.bias)

    def forward(self, light):
        # log1p tames peaky point lights (texels of hundreds) next to dim environments
        z = self.trunk(torch.log1p(light.clamp(min=0)).flatten(1))
        return [h(z) for h in self.heads]


def film(x, gb):
    gamma, beta = gb[:, :, None, None].chunk(2, dim=1)
    return x * (1.0 + gamma) + beta


# ------------------------------------------------------------------------------------ encoder/decoder

class Encoder(nn.Module):
    def __init__(self, cfg: NetConfig):
        super().__init__()
        w, x = cfg.widths, cfg.expand
        self.stem = nn.Sequential(nn.Conv2d(3 * STEM * STEM, w[0], 1), nn.ReLU(inplace=True))
        self.levels = nn.ModuleList([_stage(w[0], w[0], cfg.blocks[0], x, 1)] + [
            _stage(w[i - 1], w[i], cfg.blocks[i], x, 2) for i in range(1, len(w))])
        # The structure code: dilated blocks widen the receptive field without a further stride
        # (which would raise the padding stride), plus a global-context term.
        c = w[-1]
        self.context = nn.Sequential(InvertedResidual(c, c, x, dilation=2),
                                     InvertedResidual(c, c, x, dilation=4))
        self.global_ctx = nn.Linear(c, c)
        self.to_code = nn.Conv2d(c, cfg.code, 1)
        # Source light: attention-weighted pooling of the bottleneck, then a linear map to 16x16x3.
        self.attn = nn.Conv2d(c + cfg.code, 1, 1)
        self.feat = nn.Conv2d(c + cfg.code, 2 * cfg.light_embed, 1)
        self.to_light = nn.Sequential(nn.ReLU(inplace=True),
                                      nn.Linear(2 * cfg.light_embed, LIGHT_SIZE))

    def forward(self, image):
        x = torch.log1p(image.clamp(0.0, INPUT_CEILING))  # HDR-safe view of the image
        x = self.stem(F.pixel_unshuffle(x, STEM))
        skips = []
        for level in self.levels:
            x = level(x)
            skips.append(x)
        c = self.context(x)
        c = c + self.global_ctx(c.mean(dim=(2, 3)))[:, :, None, None]
        code = self.to_code(c)
        h = torch.cat([x, code], dim=1)
        a = torch.softmax(self.attn(h).flatten(2), dim=-1)  # (N, 1, hw)
        pooled = (self.feat(h).flatten(2) * a).sum(-1)
        # log1p(L) = softplus(.) so the paper's log-space light loss sees an unconstrained output
        light = torch.exp(F.softplus(self.to_light(pooled))) - 1.0  # expm1 has no ONNX op
        return light.view(-1, *LIGHT_SHAPE), skips, code


class Decoder(nn.Module):
    def __init__(self, cfg: NetConfig):
        super().__init__()
        w, x = cfg.widths, cfg.expand
        n = len(w)
        self.light = LightMLP(cfg.light_embed, [w[i] for i in reversed(range(n))])
        self.bottleneck = nn.Sequential(nn.Conv2d(w[-1] + cfg.code, w[-1], 1), nn.ReLU(inplace=True))
        self.blocks = nn.ModuleList()
        self.merge = nn.ModuleList()
        for i in reversed(range(n)):
            if i < n - 1:
                self.merge.append(nn.Sequential(nn.Conv2d(w[i + 1] + w[i], w[i], 1),
                                                nn.ReLU(inplace=True)))
            self.blocks.append(_stage(w[i], w[i], max(cfg.blocks[i] - 1, 1), x, 1))
        # Heads at 1/4 resolution: a 3-channel shading gain (smooth, up-sampled bilinearly), a
        # residual folded back to full resolution (pixel shuffle), and parsing logits.
        self.gain = nn.Conv2d(w[0], 3, 1)
        if cfg.residual not in ("smooth", "shuffle"):
            raise ValueError(f"unknown residual {cfg.residual!r}; use 'smooth' or 'shuffle'")
        self.shuffle = cfg.residual == "shuffle"
        self.residual = nn.Conv2d(w[0], 3 * STEM * STEM if self.shuffle else 3, 1)
        self.parsing = nn.Conv2d(w[0], cfg.classes, 1)
        if cfg.relight not in ("gain", "ratio"):
            raise ValueError(f"unknown relight head {cfg.relight!r}; use 'ratio' or 'gain'")
        self.ratio = cfg.relight == "ratio"
        if self.ratio:
            self.transport = nn.Conv2d(w[0], 9, 1)
            nn.init.zeros_(self.transport.weight)  # E = floor for every light: ratio 1 at start
            nn.init.zeros_(self.transport.bias)
            self.register_buffer("sh_basis", sh_projection(), persistent=False)
        for m in (self.gain, self.residual):
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)
        nn.init.constant_(self.gain.bias, 1.0)  # start as relit = image

    def forward(self, image, light, skips, code, source=None, with_transport: bool = False):
        """Relit image and parsing logits; ``with_transport`` adds the ratio head's transport
        (N, 9, h, w) at the decoder's resolution (training supervises it; None without the head)."""
        films = self.light(light)
        x = self.bottleneck(torch.cat([skips[-1], code], dim=1))
        for j, block in enumerate(self.blocks):
            if j > 0:
                skip = skips[-1 - j]
                # bilinear, not nearest: nearest copies of the 1/32 features left 8-pixel
                # blocks in the relit image that the skips never smoothed away
                x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
                x = self.merge[j - 1](torch.cat([x, skip], dim=1))
            x = block(film(x, films[j]))
        size = image.shape[-2:]
        g, t = self.gain(x), None
        if self.ratio:
            if source is None:
                raise ValueError("the ratio head needs the source light (the encoder's estimate)")
            t = self.transport(x)
            g = g * (self._irradiance(t, light) / self._irradiance(t, source)).clamp(max=RATIO_MAX)
        gain = F.interpolate(g, size=size, mode="bilinear", align_corners=False)
        if self.shuffle:
            residual = F.pixel_shuffle(self.residual(x), STEM)
        else:
            residual = F.interpolate(self.residual(x), size=size, mode="bilinear",
                                     align_corners=False)
        relit = gain * image.clamp(0.0, INPUT_CEILING) + residual
        parsing = F.interpolate(self.parsing(x), size=size, mode="bilinear", align_corners=False)
        # parsing as logits: the BCE loss is stabler on logits
        return (relit, parsing, t) if with_transport else (relit, parsing)

    def _irradiance(self, transport, light):
        """E_c(x) = softplus(sum_j T_j(x) L_cj): (N,9,h,w) transport, (N,3,16,16) light ->
        (N,3,h,w). The softplus keeps E positive with a soft floor of ~0.035 (unit-power lights
        give E of order 1), so the ratio stays finite in the dark."""
        coeff = light.flatten(2) @ self.sh_basis  # (N, 3, 9) SH coefficients of the light
        n, _, h, w = transport.shape
        # one batched MatMul: a broadcast multiply and sum over (N, 3, 9, h, w) cost ~4 ms/frame
        e = (coeff @ transport.flatten(2)).reshape(n, 3, h, w)
        # + a hard floor: softplus of a very negative value underflows to 0 in float32
        return F.softplus(e, beta=SOFTPLUS_BETA) + IRRADIANCE_EPS


class RelightNet(nn.Module):
    """The whole network. ``forward`` is the ONNX contract; training uses ``encode``/``decode``."""

    def __init__(self, cfg: NetConfig = NetConfig()):
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)

    def encode(self, image):
        return self.encoder(image)

    def decode(self, image, light, skips, code, source=None, with_transport: bool = False):
        """Relit image (same units as ``image / k(light)``; may be slightly negative while
        training) and parsing logits, for a unit-power light; ``source`` is the encoder's
        estimate of the image's own light (needed by the ratio head); ``with_transport`` adds
        the ratio head's transport (Decoder.forward)."""
        return self.decoder(image, light, skips, code, source, with_transport)

    def relight_by(self, image, light, skips, code, source=None):
        """Relit image under a light given in the normalised image's units (e.g. the estimated
        source light): scaled to unit power for the decoder, the output scaled back."""
        k = light_power(light).clamp(min=1e-6)
        relit, logits = self.decoder(image, light / k[:, None, None, None], skips, code, source)
        return relit * k[:, None, None, None], logits

    def forward(self, image, target_light):
        """The ONNX contract: image [N,3,H,W] (normalised), target_light [N,3,16,16] (unit power)
        -> relit [N,3,H,W], source_light [N,3,16,16], parsing [N,K,H,W] in [0,1]."""
        source, skips, code = self.encoder(image)
        return self.relight_from(image, target_light, skips, code, source)

    def relight_from(self, image, target_light, skips, code, source):
        """``forward`` after the encoder, with the source light given: the contract's estimate,
        or (a diagnostic, training.eval.evaluate --true-source) the true one."""
        relit, logits = self.decoder(image, target_light, skips, code, source)
        return relit.clamp(min=0.0), source, torch.sigmoid(logits)


# ------------------------------------------------------------------------------------------ helpers

def _solid_angles() -> torch.Tensor:
    return torch.from_numpy(lightvec.solid_angles().astype(np.float32))


def sh_projection() -> torch.Tensor:
    """(256, 9): a light vector's order-2 SH coefficients are ``light.flatten(2) @ this``
    (each cell's basis value at its centre direction times its solid angle)."""
    from ..lightstage.shading import cell_sh

    basis, omega = cell_sh(torch.float32)
    return (basis * omega[:, None]).contiguous()


def light_power(light: torch.Tensor) -> torch.Tensor:
    """k of addon.normalise.light_scale for a batch of channels-first lights [N,3,16,16]."""
    omega = _solid_angles().to(light.device, light.dtype)
    return (light * omega).sum(dim=(1, 2, 3)) / (3.0 * 4.0 * math.pi)


def to_channels_first(light_hwc: np.ndarray) -> np.ndarray:
    """(…,16,16,3) light vectors -> (…,3,16,16), the contract's layout."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(light_hwc, np.float32), -1, -3))


def count_flops(model: RelightNet, height: int, width: int) -> float:
    """Multiply-adds x 2 of the convolutions and linear layers for one frame (element-wise ops,
    resizes and activations are not counted)."""
    total = [0.0]

    def conv_hook(m, inp, out):
        k = m.kernel_size[0] * m.kernel_size[1] * (m.in_channels // m.groups)
        total[0] += 2.0 * out.numel() * k

    def linear_hook(m, inp, out):
        total[0] += 2.0 * out.numel() * m.in_features

    hooks = [m.register_forward_hook(conv_hook if isinstance(m, nn.Conv2d) else linear_hook)
             for m in model.modules() if isinstance(m, (nn.Conv2d, nn.Linear))]
    try:
        with torch.no_grad():
            model(torch.zeros(1, 3, height, width), torch.ones(1, *LIGHT_SHAPE))
    finally:
        for h in hooks:
            h.remove()
    return total[0]


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def build(preset: str = "standard", **overrides) -> RelightNet:
    return RelightNet(config_for(preset, **overrides))


__all__ = ["NetConfig", "PRESETS", "RelightNet", "build", "config_for", "count_flops",
           "light_power", "parameter_count", "to_channels_first"]
