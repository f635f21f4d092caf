"""The intrinsic network: one image in, the buffers the renderer needs out.

A U-Net built for a CPU (dense 3x3 convolutions, which run well in bf16 here, bilinear upsampling,
five levels). Input: the normalised linear image (addon/intrinsic.py scales a crop so its 90th
luminance percentile is 0.6); the first operation encodes it with a 1/2.2 power, the way the
camera data it must generalise to is distributed. Outputs, all at the input's size:

* ``normal`` (3): unit surface normal in the camera frame (+X right, +Y up, +Z toward the camera);
* ``height`` (1): height toward the camera in pixels, up to a constant (only differences matter);
* ``albedo`` (3): reflectance in (0, 1), up to a per-channel gain (one image cannot tell albedo
  from light power; the renderer only uses its variations);
* ``parsing`` (2, or 3 with ``hair``): sigmoid probabilities of the portrait foreground (the
  matte) and face skin, and of hair (hair_head);
* ``transfer`` (16): the light that reaches each pixel as order-3 SH coefficients (visibility
  times cosine: addon.intrinsic's light transport; data.transfer_matrix), so occlusion by the
  nose, brows, jaw and hair is learnt from the light stage rather than guessed from the height.

With ``albedo`` the albedo's logit is refined by a small head of its own (albedo_head), which
a network trained without it gains with every other output unchanged.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as tf

from addon.intrinsic import TRANSFER_BAND, TRANSFER_CHANNELS, TRANSFER_ORDER, sh_basis

WIDTHS = {"small": (16, 32, 64, 96, 128), "standard": (24, 48, 96, 128, 192)}
STRIDE = 16
OUTPUTS = ("normal", "height", "albedo", "parsing", "transfer")
HEAD = 3 + 1 + 3 + 2 + TRANSFER_CHANNELS
CLASSES = ("foreground", "skin")
HAIR_CLASSES = CLASSES + ("hair",)
HAIR_WIDTH = 8
ALBEDO_WIDTH = 12


def block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def hair_head(w: tuple[int, ...]) -> nn.Sequential:
    """The hair class's own small head: it reads the two finest decoder blocks' features at half
    the input's size (the finest one averaged down) and its logit is enlarged to the input's, so
    it costs a quarter of what it would at full size, and a network trained without it gains it
    with every other output unchanged (``train --train-only hair``). Hair below the chin is what
    the renderer needs it for: there the neck and clothes, which the light stage renders
    Lambert, stand beside it, and only a class tells them apart."""
    return nn.Sequential(nn.Conv2d(w[0] + w[1], 2 * HAIR_WIDTH, 1), nn.ReLU(inplace=True),
                         nn.Conv2d(2 * HAIR_WIDTH, HAIR_WIDTH, 3, 1, 1), nn.ReLU(inplace=True),
                         nn.Conv2d(HAIR_WIDTH, 1, 1))


def albedo_head(w: tuple[int, ...]) -> nn.Sequential:
    """The albedo's own small head: from the full-resolution decoder block's features beside
    the encoded input image, a correction added to the albedo's logit (its last convolution
    starts at zero, so a network gains the head with its albedo unchanged). The shared output
    head reads the albedo linearly off features that also carry the normals, height and
    transfer; this one sees each pixel's 3x3 neighbourhood and the picture itself, to take the
    shading the shared head leaves in the albedo out. Trained alone (``train --train-only
    albedo``), it refines the albedo while the other buffers stay the network's own: the
    renderer's up/down balance on real faces lives in those."""
    last = nn.Conv2d(ALBEDO_WIDTH, 3, 1)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(nn.Conv2d(w[0] + 3, ALBEDO_WIDTH, 3, 1, 1), nn.ReLU(inplace=True),
                         nn.Conv2d(ALBEDO_WIDTH, ALBEDO_WIDTH, 1), nn.ReLU(inplace=True), last)


class IntrinsicNet(nn.Module):
    """``transfer`` False: the network without the transfer (networks trained before it had
    none; their files keep four outputs when re-exported). ``hair``: a third parsing class,
    hair (hair_head). ``albedo``: the albedo's own refining head (albedo_head)."""

    def __init__(self, width: str = "standard", transfer: bool = True, hair: bool = False,
                 albedo: bool = False):
        super().__init__()
        w = WIDTHS[width]
        self.width = width
        self.transfer = transfer
        self.hair = hair
        self.albedo = albedo
        self.enc = nn.ModuleList([block(3, w[0])] + [block(w[i - 1], w[i], 2)
                                                     for i in range(1, len(w))])
        self.dec = nn.ModuleList([block(w[i + 1] + w[i], w[i]) for i in range(len(w) - 1)])
        self.head = nn.Conv2d(w[0], HEAD if transfer else HEAD - TRANSFER_CHANNELS, 1)
        if hair:
            self.hair_head = hair_head(w)
        if albedo:
            self.albedo_head = albedo_head(w)

    @property
    def classes(self) -> tuple[str, ...]:
        return HAIR_CLASSES if self.hair else CLASSES

    def forward(self, image: torch.Tensor):
        x = encoded = image.clamp(0.0, 1.0).clamp(min=1e-6) ** (1 / 2.2) - 0.5
        skips = []
        for enc in self.enc:
            x = enc(x)
            skips.append(x)
        x = skips.pop()
        coarse = None
        for i in reversed(range(len(self.dec))):
            s = skips[i]
            coarse = x if i == 0 else coarse  # the second-finest block's output
            x = tf.interpolate(x, size=s.shape[-2:], mode="bilinear", align_corners=False)
            x = self.dec[i](torch.cat([x, s], 1))
        out = self.head(x).float()
        normal = tf.normalize(out[:, 0:3], dim=1, eps=1e-6)
        height = out[:, 3:4] * 10.0
        logit = out[:, 4:7]
        if self.albedo:
            logit = logit + self.albedo_head(torch.cat([x, encoded.to(x.dtype)], 1)).float()
        albedo = torch.sigmoid(logit)
        parsing = torch.sigmoid(out[:, 7:9])
        if self.hair:
            fine = tf.avg_pool2d(x, 2)  # sizes are multiples of STRIDE
            hair = self.hair_head(torch.cat([fine, coarse], 1))
            hair = tf.interpolate(hair, size=x.shape[-2:], mode="bilinear", align_corners=False)
            parsing = torch.cat([parsing, torch.sigmoid(hair.float())], 1)
        if not self.transfer:
            return normal, height, albedo, parsing
        return normal, height, albedo, parsing, unoccluded(normal.detach()) + out[:, 9:HEAD]


def has_transfer(state_dict: dict) -> bool:
    """Whether a saved network predicts the transfer."""
    return state_dict["head.weight"].shape[0] == HEAD


def has_hair(state_dict: dict) -> bool:
    """Whether a saved network predicts the hair class."""
    return any(k.startswith("hair_head.") for k in state_dict)


def has_albedo_head(state_dict: dict) -> bool:
    """Whether a saved network refines its albedo with a head of its own."""
    return any(k.startswith("albedo_head.") for k in state_dict)


_TRANSFER_BAND = torch.from_numpy(TRANSFER_BAND.copy())


def unoccluded(normal: torch.Tensor) -> torch.Tensor:
    """(B, 16, H, W) the transfer of unoccluded Lambertian pixels with these normals: the
    network's transfer is this plus what it predicts occlusion takes away (at initialisation,
    nothing: the renderer's plain Lambert shading)."""
    band = _TRANSFER_BAND.to(normal.device, normal.dtype).view(1, -1, 1, 1)
    return band * sh_basis(normal.unbind(1), TRANSFER_ORDER, stack=lambda v: torch.stack(v, 1))


def load_weights(net: IntrinsicNet, state_dict: dict) -> None:
    """Load a state dict into ``net``; one saved before the network predicted the transfer (a
    head of 9 channels) keeps its buffers' weights, and the transfer's channels start at zero
    (the unoccluded transfer of the predicted normals). A network without the transfer takes
    the buffers' channels of one with it. A network with the hair class loaded from one
    without it keeps its hair head as initialised, and so does the albedo's head (albedo_head:
    the albedo as the saved network's)."""
    if net.hair and not has_hair(state_dict):
        state_dict = {**state_dict, **{f"hair_head.{k}": v
                                       for k, v in net.hair_head.state_dict().items()}}
    if net.albedo and not has_albedo_head(state_dict):
        state_dict = {**state_dict, **{f"albedo_head.{k}": v
                                       for k, v in net.albedo_head.state_dict().items()}}
    head = state_dict.get("head.weight")
    if head is not None and not net.transfer and head.shape[0] == HEAD:
        keep = HEAD - TRANSFER_CHANNELS
        state_dict = {**state_dict, "head.weight": head[:keep],
                      "head.bias": state_dict["head.bias"][:keep]}
    elif head is not None and head.shape[0] < HEAD and net.transfer:
        state_dict = dict(state_dict)
        for name in ("head.weight", "head.bias"):
            full = torch.zeros_like(net.state_dict()[name])
            full[:state_dict[name].shape[0]] = state_dict[name]
            state_dict[name] = full
    net.load_state_dict(state_dict)


TRANSFER_WEIGHT = 2.0  # the transfer's L1 (its coefficients are about 0.1-1) in the total
ALBEDO_WEIGHT = 0.5    # the albedo's log L1 (up to a gain per channel) in the total
GRADIENT_SCALES = (2, 4, 8)  # block sizes the normals are pooled over before their differences
HAIR_TARGET = 9 + TRANSFER_CHANNELS  # the hair label's channel in the target (data.TARGETS)


def normal_gradient(normal: torch.Tensor, t_n: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
    """How far the predicted face's curvature is from the truth's: the normals averaged over the
    face skin ``face`` (B, 1, H, W) in blocks of GRADIENT_SCALES pixels, and the mean absolute
    difference of neighbouring blocks' differences (right and down), predicted against true, over
    blocks wholly on the skin. Pooled, because the light stage's per-pixel normals carry the skin's
    pores and the mesh's facets (blurring the true normals by 5 px moves them as far as the
    network's error at one pixel, a third of it at four): the nose, brows and eye sockets are what
    a relit face shows."""
    out = normal.new_zeros(())
    for k in GRADIENT_SCALES:
        wk = tf.avg_pool2d(face, k)
        whole = (wk > 0.99).float()
        p = tf.avg_pool2d(normal * face, k) / wk.clamp(min=1e-6)
        t = tf.avg_pool2d(t_n * face, k) / wk.clamp(min=1e-6)
        for dim in (2, 3):
            n = p.size(dim) - 1
            if n < 1:
                continue
            dp = p.narrow(dim, 1, n) - p.narrow(dim, 0, n)
            dt = t.narrow(dim, 1, n) - t.narrow(dim, 0, n)
            pw = whole.narrow(dim, 1, n) * whole.narrow(dim, 0, n)
            out = out + ((dp - dt).abs() * pw).sum() / pw.sum().clamp(min=1.0)
    return out


LOW_SIGMA = 6.0  # pixels at 128: the band of the face's shape that sets a relit face's up/down


def gaussian_kernel(sigma: float) -> torch.Tensor:
    """A normalised 1-D Gaussian of ``sigma`` pixels, cut at three sigma."""
    r = max(1, int(round(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def masked_low(x: torch.Tensor, mask: torch.Tensor,
               sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(the Gaussian low band of ``x`` (B, C, H, W) over ``mask`` (B, 1, H, W) alone, the
    blurred mask): the blur of x * mask divided by the blur of the mask, so the backdrop
    does not leak into the subject's edge. Edges replicate."""
    k = gaussian_kernel(sigma).to(x)
    r = k.numel() // 2
    both = torch.cat([x * mask, mask], 1)
    c = both.size(1)
    both = tf.pad(both, (r, r, r, r), mode="replicate")
    both = tf.conv2d(both, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    both = tf.conv2d(both, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    m = both[:, -1:]
    return both[:, :-1] / m.clamp(min=1e-6), m


def normal_low_band(normal: torch.Tensor, t_n: torch.Tensor, fg: torch.Tensor,
                    sigma: float = LOW_SIGMA, up_weight: float = 1.0) -> torch.Tensor:
    """How far the predicted normals' Gaussian low band (``sigma`` pixels, over the subject
    ``fg`` alone: masked_low) is from the truth's: the mean absolute difference per component
    (the up/down one ``up_weight`` times) where the blurred subject covers at least half. On real
    faces this band (the face's shape at a few pixels of 128) sets a relit face's up/down
    balance, its detail the rest (training.eval.yale_normals --low-sigma)."""
    both, m = masked_low(torch.cat([normal, t_n], 1), fg, sigma)  # one pass, one mask's blur
    w = (m > 0.5).float() * fg
    err = (both[:, :3] - both[:, 3:]).abs()
    if up_weight != 1.0:
        err = err * err.new_tensor([1.0, up_weight, 1.0]).view(1, 3, 1, 1)
    return (err * w).sum() / (3 * w.sum()).clamp(min=1.0)


def losses(pred, target: torch.Tensor, fg: torch.Tensor, face_weight: float = 0.0,
           gradient_weight: float = 0.0, up_weight: float = 1.0,
           albedo_weight: float = ALBEDO_WEIGHT, low_weight: float = 0.0,
           low_sigma: float = LOW_SIGMA) -> dict:
    """Per-buffer losses against the light stage's exact buffers (data.TARGETS order: normal 3,
    height 1, albedo 3, matte 1, face 1, transfer 16, hair 1); ``fg`` (B, 1, H, W) where the
    subject's buffers exist. The hair class's loss (``hair``, over the whole picture) joins the
    total when the network predicts it.
    ``face_weight``: the normal losses count face-skin pixels 1 + face_weight times (the face is a
    third of the subject and carries the shading a relit face shows); ``gradient_weight``: the
    normals' differences between neighbours on the face skin (normal_gradient) join the normal
    loss; ``up_weight``: the up/down component's absolute error counts this many times the
    others' (a face varies less up and down than across, so a flattened up/down shape costs
    little in the angle, yet it sets the balance of a light from above or below);
    ``albedo_weight``: the albedo loss's weight in the total; ``low_weight``: the normals' low
    band's error (normal_low_band, ``low_sigma`` pixels) joins the normal loss this many times."""
    normal, height, albedo, parsing, *transfer = pred
    n = fg.sum((2, 3)).clamp(min=1.0)  # (B, 1)

    def mean_fg(x):  # (B, C, H, W) -> (B, C) mean over the foreground
        return (x * fg).sum((2, 3)) / n

    t_n, t_h, t_a = target[:, 0:3], target[:, 3:4], target[:, 4:7]
    t_m, t_f = target[:, 7:8], target[:, 8:9]
    cos = (normal * t_n).sum(1, keepdim=True)
    w = fg * (1.0 + face_weight * t_f)  # fg alone when face_weight is 0
    nw = w.sum((2, 3)).clamp(min=1.0)

    def mean_w(x):
        return (x * w).sum((2, 3)) / nw

    err = (normal - t_n).abs()
    if up_weight != 1.0:
        err = err * err.new_tensor([1.0, up_weight, 1.0]).view(1, 3, 1, 1)
    l_normal = mean_w(1.0 - cos).mean() + 0.5 * mean_w(err).mean()
    if gradient_weight:
        l_normal = l_normal + gradient_weight * normal_gradient(normal, t_n, fg * t_f)
    if low_weight:
        l_normal = l_normal + low_weight * normal_low_band(normal, t_n, fg, low_sigma, up_weight)
    d = height - t_h
    d = d - mean_fg(d)[..., None, None]
    l_height = mean_fg(d.abs()).mean() / 10.0
    la = torch.log(albedo + 0.02) - torch.log(t_a + 0.02)
    la = la - mean_fg(la)[..., None, None]  # albedo up to a gain per channel
    l_albedo = mean_fg(la.abs()).mean()
    p = parsing.clamp(1e-5, 1 - 1e-5)
    l_matte = tf.binary_cross_entropy(p[:, 0:1], t_m)
    l_face = tf.binary_cross_entropy(p[:, 1:2], t_f)
    l_hair = (tf.binary_cross_entropy(p[:, 2:3], target[:, HAIR_TARGET:HAIR_TARGET + 1])
              if p.shape[1] > 2 else normal.new_zeros(()))
    l_transfer = (mean_fg((transfer[0] - target[:, 9:9 + TRANSFER_CHANNELS]).abs()).mean()
                  if transfer else normal.new_zeros(()))
    total = (l_normal + l_height + albedo_weight * l_albedo + 0.5 * l_matte + 0.5 * l_face
             + TRANSFER_WEIGHT * l_transfer + 0.5 * l_hair)
    with torch.no_grad():
        ang = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
        angle = mean_fg(ang).mean()
    return {"total": total, "normal": l_normal, "height": l_height, "albedo": l_albedo,
            "matte": l_matte, "face": l_face, "transfer": l_transfer, "hair": l_hair,
            "normal_deg": angle}
