"""The paper's training objective (sec. 4.1-4.4), all terms weighted 1.0.

    basic     0.5 ||log(1+L) - log(1+L_hat)||^2 + ||M (I^k - I~^k)||_1 + ||M (I^i - I^^i)||_1
    latent    ||e^_t - e~_t||^2, e~_t the structure code of the relit image encoded again
    parsing   binary cross-entropy of the parsing channels
    temporal  flow-warped L1 between frames t and t+1, both directions, for the target-relit images
              and the self-relit images under both source lights (the paper's cross manner)
    adv       WGAN: a DCGAN-bodied critic without its final activation scores (source, relit, light)

Norms are means (per pixel, texel or code element), so every term is O(1) whatever the image size
and the weights of 1.0 stay meaningful. Every image here is in the network's normalised units
(training.model.units.normalise_sample): inputs ``img / s``, target-relit ground truth
``gt / (s k)``, self-relit ground truth the normalised input itself, source lights ``light / s``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from . import warp
from .network import RelightNet, light_power

EPS = 1e-6


@dataclass(frozen=True)
class Switches:
    """The paper's ablations. ``sampling`` is applied by the data (the light triplets); it is kept
    here so that one object records the whole variant."""

    structure: bool = True  # latent (structure self-supervision) loss
    temporal: bool = True
    parsing: bool = True
    adversarial: bool = True
    sampling: bool = True
    # Not in the paper: supervise the ratio head's per-pixel SH transport with the light stage's
    # own (its OLAT transfer projected to order-2 SH; training/lightstage/pairs.py transport).
    transport: bool = False

    @classmethod
    def ablation(cls, name: str) -> "Switches":
        names = {"full": {}, "no_structure": {"structure": False}, "no_temporal": {"temporal": False},
                 "no_parsing": {"parsing": False}, "no_sampling": {"sampling": False},
                 # diagnosis only: the basic term alone (is another term fighting it?)
                 "basic_only": {"structure": False, "temporal": False, "parsing": False,
                                "adversarial": False}}
        if name not in names:
            raise ValueError(f"unknown ablation {name!r}; choose one of {sorted(names)}")
        return cls(**names[name])

    def to_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------------------- terms

def light_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """0.5 (log(1+L) - log(1+L_hat))^2, mean over texels and channels."""
    return 0.5 * (torch.log1p(target.clamp(min=0)) - torch.log1p(pred.clamp(min=0))).pow(2).mean()


def masked_l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean |pred - target| over the pixels where mask > 0 (mask [N,1,H,W], soft weights allowed)."""
    num = ((pred - target).abs() * mask).sum()
    return num / (mask.sum() * pred.shape[1] + EPS)


def parsing_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return F.binary_cross_entropy_with_logits(logits, target.clamp(0.0, 1.0))


def latent_loss(code: torch.Tensor, code_again: torch.Tensor) -> torch.Tensor:
    return (code - code_again).pow(2).mean()


def temporal_pair(a_t: torch.Tensor, a_t1: torch.Tensor, flow_fw: torch.Tensor,
                  flow_bw: torch.Tensor, valid_fw: torch.Tensor, valid_bw: torch.Tensor
                  ) -> torch.Tensor:
    """||f_{t,t+1}(a_t) - a_t1||_1 + ||f_{t+1,t}(a_t1) - a_t||_1 over valid pixels."""
    fwd = masked_l1(warp.to_next(a_t, flow_bw), a_t1, valid_bw * warp.in_bounds(flow_bw))
    bwd = masked_l1(warp.to_previous(a_t1, flow_fw), a_t, valid_fw * warp.in_bounds(flow_fw))
    return fwd + bwd


# ------------------------------------------------------------------------------------------ critic

class Critic(nn.Module):
    """DCGAN discriminator body (strided 4x4 convs, batch norm, leaky ReLU) with the final sigmoid
    removed (WGAN). Input: the triplet (source, relit, light) as 9 channels, images as log(1+x)
    and the light stretched over the image; the score is averaged over the remaining positions,
    so any input of 32 pixels or more works."""

    def __init__(self, width: int = 32, depth: int = 4):
        super().__init__()
        layers, c = [], 9
        for i in range(depth):
            out = width * 2 ** i
            layers.append(nn.Conv2d(c, out, 4, 2, 1, bias=i == 0))
            if i > 0:
                layers.append(nn.BatchNorm2d(out))
            layers.append(nn.LeakyReLU(0.2, inplace=True))
            c = out
        layers.append(nn.Conv2d(c, 1, 3, 1, 1))
        self.body = nn.Sequential(*layers)

    def forward(self, source, relit, light):
        size = source.shape[-2:]
        light_map = F.interpolate(torch.log1p(light.clamp(min=0)), size=size, mode="nearest")
        x = torch.cat([torch.log1p(source.clamp(min=0)), torch.log1p(relit.clamp(min=0)),
                       light_map], dim=1)
        return self.body(x).mean(dim=(1, 2, 3))

    @torch.no_grad()
    def clip_weights(self, bound: float = 0.01) -> None:
        for p in self.parameters():
            p.clamp_(-bound, bound)


def critic_loss(critic: Critic, source, real, fake, light) -> torch.Tensor:
    """L_adv_D = -D(I^i, I^k, L^k) + D(I^i, I~^k, L^k): updates the critic only."""
    return (critic(source, fake.detach(), light) - critic(source, real, light)).mean()


def generator_adv_loss(critic: Critic, source, fake, light) -> torch.Tensor:
    """L_adv_G = -D(I^i, I~^k, L^k): updates the network only."""
    return -critic(source, fake, light).mean()


def make_critic_optimizer(critic: Critic, lr: float = 5e-5) -> torch.optim.Optimizer:
    return torch.optim.RMSprop(critic.parameters(), lr=lr)


# ------------------------------------------------------------------------------- whole objective

def _decode_many(net: RelightNet, image, skips, code, source, lights, scales):
    """Decode one frame under several lights in one batched pass. ``lights`` are unit-power;
    each output is multiplied by its scale (1 for a target light, k for an estimated one).
    ``source`` is the frame's estimated own light (the ratio head's denominator). Returns the
    outputs, the parsing logits and the ratio head's transport of every decode (None without
    one)."""
    n = len(lights)
    rep = lambda t: t.repeat(n, *([1] * (t.dim() - 1)))  # noqa: E731
    relit, logits, transport = net.decode(rep(image), torch.cat(lights, 0),
                                          [rep(s) for s in skips], rep(code), rep(source),
                                          with_transport=True)
    scales = torch.cat(scales, 0)[:, None, None, None]
    return list((relit * scales).chunk(n, 0)), logits.chunk(n, 0)[0], transport


def transport_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Masked L1 between the predicted transport (n*N, 9, h, w) at the decoder's resolution (n
    decodes of the same N frames) and the light stage's (N, 9, H, W), area-averaged to h x w."""
    f = target.shape[-1] // pred.shape[-1]
    t = F.avg_pool2d(target, f) if f > 1 else target
    m = F.avg_pool2d(mask, f) if f > 1 else mask
    n = pred.shape[0] // t.shape[0]
    t, m = t.repeat(n, 1, 1, 1), (m > 0.5).float().repeat(n, 1, 1, 1)
    return ((pred - t).abs() * m).sum() / (m.sum() * pred.shape[1]).clamp(min=1.0)


def _unit(light):
    k = light_power(light).clamp(min=EPS)
    return light / k[:, None, None, None], k


def generator_objective(net: RelightNet, b: dict, sw: Switches, critic: Critic | None = None,
                        adv_weight: float = 1.0):
    """All generator terms for a batch of frame pairs. Returns (total, parts, fake) where ``parts``
    holds each term as a float and ``fake`` is the target-relit frame t for the critic step."""
    light_t, skips_t, code_t = net.encode(b["img_t"])
    light_t1, skips_t1, code_t1 = net.encode(b["img_t1"])
    unit_i, k_i = _unit(light_t)
    unit_j, k_j = _unit(light_t1)
    ones = torch.ones_like(k_i)
    target = b["light_k"]
    if sw.temporal:  # each frame under L^k and under both estimated source lights
        lights_t, scales_t = [target, unit_i, unit_j], [ones, k_i, k_j]
        lights_t1, scales_t1 = [target, unit_j, unit_i], [ones, k_j, k_i]
    else:
        lights_t, scales_t = [target, unit_i], [ones, k_i]
        lights_t1, scales_t1 = [target, unit_j], [ones, k_j]
    out_t, logits_t, tr_t = _decode_many(net, b["img_t"], skips_t, code_t, light_t, lights_t,
                                         scales_t)
    out_t1, logits_t1, tr_t1 = _decode_many(net, b["img_t1"], skips_t1, code_t1, light_t1,
                                            lights_t1, scales_t1)

    parts = {}
    m_t, m_t1 = b["mask_t"], b["mask_t1"]
    parts["basic"] = (light_loss(light_t, b["src_t"]) + light_loss(light_t1, b["src_t1"])
                      + masked_l1(out_t[0], b["gt_t"], m_t) + masked_l1(out_t1[0], b["gt_t1"], m_t1)
                      + masked_l1(out_t[1], b["img_t"], m_t)
                      + masked_l1(out_t1[1], b["img_t1"], m_t1))
    if sw.structure:
        _, _, code_again = net.encode(out_t[0])
        _, _, code_again1 = net.encode(out_t1[0])
        parts["latent"] = latent_loss(code_t, code_again) + latent_loss(code_t1, code_again1)
    if sw.transport and tr_t is not None and "transport_t" in b:
        parts["transport"] = (transport_loss(tr_t, b["transport_t"], b["mask_t"])
                              + transport_loss(tr_t1, b["transport_t1"], b["mask_t1"]))
    if sw.parsing:
        parts["parsing"] = (parsing_loss(logits_t, b["parsing_t"])
                            + parsing_loss(logits_t1, b["parsing_t1"]))
    if sw.temporal:
        flows = (b["flow_fw"], b["flow_bw"], b["valid_fw"], b["valid_bw"])
        # target-relit pair, then self-relit under L^i (t: own, t+1: cross), then under L^j
        parts["temporal"] = (temporal_pair(out_t[0], out_t1[0], *flows)
                             + temporal_pair(out_t[1], out_t1[2], *flows)
                             + temporal_pair(out_t[2], out_t1[1], *flows))
    if sw.adversarial and critic is not None and adv_weight > 0:
        parts["adv"] = adv_weight * generator_adv_loss(critic, b["img_t"], out_t[0], target)
    total = sum(parts.values())
    return total, {k: float(v.detach()) for k, v in parts.items()}, out_t[0].detach()
