"""Train the intrinsic network on light-stage frames (training/intrinsic/data.py).

    .venv/bin/python -m training.intrinsic.train --minutes 60 --out runs/intrinsic-standard

Each step relights random frames under random lights, passes them through a simulated camera
(training/intrinsic/camera.py: exposure, white balance, tone curve, sRGB, noise, blur, JPEG, the
product's decode back to linear), normalises them as the product does (addon.intrinsic), and
supervises every buffer with the light stage's exact values. bf16 autocast on the CPU (dense 3x3
convolutions run about twice as fast in bf16 on processors with AVX-512 bf16). The run keeps an
exponential moving average of the weights and chooses ``best.pt`` on held-out val identities.

A step's batch is a pure function of (seed, step) (``step_batch``), so ``--workers N`` (batches
made in N processes ahead of the network) and ``--device cuda`` train on the same samples as one
thread on the CPU does:

    python -m training.intrinsic.train --device cuda --workers 15 --batch 24 ...
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import subprocess
import time

import torch

from addon import intrinsic as renderer

from . import camera, data
from .model import ALBEDO_WEIGHT, HAIR_TARGET, LOW_SIGMA, IntrinsicNet, load_weights, losses


def normalise_batch(img: torch.Tensor) -> torch.Tensor:
    """The product's crop normalisation (addon.intrinsic.exposure_scale), per image."""
    lum = (img * torch.tensor(renderer.LUMA).view(1, 3, 1, 1)).sum(1).flatten(1)
    q = torch.quantile(lum, renderer.INPUT_QUANTILE, dim=1)
    scale = renderer.INPUT_LEVEL / q.clamp(min=1e-8)
    scale = torch.where(q > 1e-8, scale, torch.ones_like(scale))
    return img * scale.view(-1, 1, 1, 1)


ZOOM = (1.0, 1.7)  # tighter framings than the light stage's camera gives (a face filling the crop)


def zoom(batch: dict, gen: torch.Generator, p: float = 0.5) -> dict:
    """Zoom a random share ``p`` of the batch into a random sub-square (scale in ZOOM), image and
    buffers alike: normals are renormalised, heights (in pixels) scale with the zoom."""
    n = batch["image"].shape[0]
    pick = torch.rand(n, generator=gen) < p
    if not bool(pick.any()):
        return batch
    f = ZOOM[0] + (ZOOM[1] - ZOOM[0]) * torch.rand(n, generator=gen)
    f = torch.where(pick, f, torch.ones_like(f))
    room = 1.0 - 1.0 / f
    t = (torch.rand(n, 2, generator=gen) * 2 - 1) * room[:, None]
    theta = torch.zeros(n, 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0 / f
    theta[:, :, 2] = t
    grid = torch.nn.functional.affine_grid(theta, list(batch["image"].shape), align_corners=False)

    def warp(x, mode="bilinear"):
        return torch.nn.functional.grid_sample(x, grid, mode=mode, padding_mode="border",
                                               align_corners=False)

    out = dict(batch)
    out["image"] = warp(batch["image"])
    tgt = warp(batch["target"])
    fg = warp(batch["fg"], "nearest")
    tgt[:, 0:3] = torch.nn.functional.normalize(tgt[:, 0:3], dim=1) * fg
    tgt[:, 3:4] = tgt[:, 3:4] * f.view(-1, 1, 1, 1)
    tgt[:, 8:9] = (tgt[:, 8:9] > 0.5).float()
    tgt[:, HAIR_TARGET] = (tgt[:, HAIR_TARGET] > 0.5).float()
    out["target"], out["fg"] = tgt, fg
    return out


CUT_SIDE_P = 0.6  # chance that each side of a cut sample's frame crosses the subject
CUT_REACH = (-0.15, 0.35)  # where that side lands: face-box edge plus this share of the face's size


def frame_cut(batch: dict, gen: torch.Generator, p: float = 0.3) -> dict:
    """The frame's edge through the subject, for a random share ``p`` of the batch: a tight photo
    (a face filling its frame, CroppedYale's crops) or a head cut by the top of a phone video
    reaches the network with black room beyond the frame's edge (addon.portrait.crop_planar).
    Each side of a picked sample lands, with CUT_SIDE_P, near the face box's edge; ``inside``
    (B, 1, H, W) says which pixels stay. Beyond the edge nothing is seen: no buffer losses there
    and no subject in the matte and face targets (the product zeroes both there too)."""
    img = batch["image"]
    n, _, h, w = img.shape
    inside = torch.ones(n, 1, h, w)
    face = batch["target"][:, 8] > 0.5
    pick = torch.rand(n, generator=gen) < p
    ys, xs = torch.arange(h).view(h, 1), torch.arange(w).view(1, w)
    for i in torch.nonzero(pick).flatten().tolist():
        rows, cols = torch.nonzero(face[i].any(1)).flatten(), torch.nonzero(face[i].any(0)).flatten()
        if len(rows) < 4 or len(cols) < 4:
            continue
        size = float(max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1)
        u = torch.rand(4, generator=gen)
        reach = CUT_REACH[0] + (CUT_REACH[1] - CUT_REACH[0]) * torch.rand(4, generator=gen)
        edge = [float(e) for e in reach * size]
        top = rows[0] - edge[0] if u[0] < CUT_SIDE_P else -1
        bottom = rows[-1] + edge[1] if u[1] < CUT_SIDE_P else h
        left = cols[0] - edge[2] if u[2] < CUT_SIDE_P else -1
        right = cols[-1] + edge[3] if u[3] < CUT_SIDE_P else w
        inside[i, 0] = ((ys >= top) & (ys <= bottom) & (xs >= left) & (xs <= right)).float()
    out = dict(batch)
    out["inside"] = inside
    out["fg"] = batch["fg"] * inside
    tgt = batch["target"].clone()
    tgt[:, 7:9] *= inside
    tgt[:, HAIR_TARGET:HAIR_TARGET + 1] *= inside
    out["target"] = tgt
    return out


def prepare(batch: dict, gen: torch.Generator, strength: float = 1.0) -> torch.Tensor:
    img = camera.camera_pipeline(batch["image"], gen, strength)
    img = camera.greyscale(img, gen, 0.15)
    if "inside" in batch:  # black beyond the frame's edge, after the camera, as the product pads
        img = img * batch["inside"]
    return normalise_batch(img)


# Crops normalised brighter than the product's INPUT_LEVEL (--bright): up to this level,
# log-uniform, so the lit side's highlights clip at the network's input clamp. The shipped
# network, trained at INPUT_LEVEL alone, relights real faces' up/down balance better when fed
# brighter crops, at a cost in PSNR beyond about 0.8 (`training.eval.yale --split tune
# --input-level L`); trained on them, it relights that balance worse than the same training
# without them (models/research/portrait-bright.json's note).
BRIGHT_MAX = 1.2


def brighten(img: torch.Tensor, gen: torch.Generator, p: float) -> torch.Tensor:
    """A random share ``p`` of the normalised batch ``img`` (N, 3, H, W) made brighter: times a
    factor log-uniform in [1, BRIGHT_MAX / INPUT_LEVEL]."""
    n = img.shape[0]
    pick = torch.rand(n, generator=gen) < p
    top = math.log(BRIGHT_MAX / renderer.INPUT_LEVEL)
    f = torch.exp(top * torch.rand(n, generator=gen))
    return img * torch.where(pick, f, torch.ones_like(f)).view(-1, 1, 1, 1)


def step_batch(ds, a, step: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(input, target, fg) of the run's batch ``step`` (counted from --start-step's batch index):
    the frames, lights, zoom, frame cut and camera all drawn from (seed, step) alone."""
    first = (a.start_step + step) * a.batch
    gen = torch.Generator().manual_seed(int(a.seed) * 1_000_003 + a.start_step + step)
    batch = ds.batch(range(first, first + a.batch))
    if a.zoom > 0:
        batch = zoom(batch, gen, a.zoom)
    if a.cut > 0:
        batch = frame_cut(batch, gen, a.cut)
    img = prepare(batch, gen)
    if a.bright > 0:  # drawn last: the rest of the batch is as without it
        img = brighten(img, gen, a.bright)
    return img, batch["target"], batch["fg"]


class StepBatches(torch.utils.data.IterableDataset):
    """step_batch for steps 0, 1, 2, ... in order, shared out among a DataLoader's workers
    (worker k of n makes steps k, k + n, ...; the loader takes them in turn, so in order)."""

    def __init__(self, ds, a):
        super().__init__()
        self.ds, self.a = ds, a

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        if info:  # a worker process: one thread each (the run's --threads stay the network's)
            torch.set_num_threads(1)
        k, n = (info.id, info.num_workers) if info else (0, 1)
        step = k
        while True:
            yield step_batch(self.ds, self.a, step)
            step += n


def batches(ds, a):
    """The run's batches in step order: made inline, or by --workers processes ahead of use."""
    if not a.workers:
        yield from StepBatches(ds, a)
        return
    loader = torch.utils.data.DataLoader(StepBatches(ds, a), batch_size=None,
                                         num_workers=a.workers, prefetch_factor=4,
                                         persistent_workers=True,
                                         pin_memory=a.device.startswith("cuda"))
    yield from loader


class EMA:
    def __init__(self, model: torch.nn.Module, decay: float):
        self.decay = decay
        self.shadow = {k: v.detach().clone() for k, v in model.state_dict().items()}

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int):
        d = min(self.decay, (1 + step) / (10 + step))
        for k, v in model.state_dict().items():
            if v.dtype.is_floating_point:
                self.shadow[k].mul_(d).add_(v.detach(), alpha=1 - d)
            else:
                self.shadow[k].copy_(v)


# What --train-only leaves to train (module name prefixes): the rest keeps its weights and its
# batch statistics. "last": the full-resolution decoder block and the output head, which see
# only a few pixels around each one; "decoder": every decoder block and the head. Meant to
# refine the buffers while the encoder's reading of a face's large-scale shape stays; it does
# not guarantee it: 2,500 steps of "decoder" (--albedo-weight 1.5) from the shipped network
# moved the CroppedYale tune subjects' top/bottom balance 0.808 -> 0.794. "hair": only the hair
# class's head (model.hair_head), so every other output stays exactly the --init network's;
# "albedo": only the albedo's own head (model.albedo_head), likewise.
TRAIN_ONLY = {"all": None, "decoder": ("dec", "head"), "last": ("dec.0", "head"),
              "hair": ("hair_head",), "albedo": ("albedo_head",)}


# The buffers --learn may leave to the light stage under --hold-others (the albedo always is).
LEARNABLE = ("transfer", "normal", "height")


def held_target(teacher: torch.nn.Module, inp: torch.Tensor, target: torch.Tensor,
                learn: tuple[str, ...] = ()) -> torch.Tensor:
    """``target`` (data.TARGETS' channels) with every buffer but the albedo and ``learn``
    (LEARNABLE's) replaced by ``teacher``'s prediction for ``inp`` (--hold-others): the others
    are then held to the --init network's own while those learn from the light stage, and
    every layer may change to serve them. Channels the teacher does not predict (the transfer
    or the hair class of a network without them) keep the light stage's."""
    with torch.no_grad():
        normal, height, _, parsing, *transfer = teacher(inp)
    out = target.clone()
    if "normal" not in learn:
        out[:, 0:3] = normal
    if "height" not in learn:
        out[:, 3:4] = height
    out[:, 7:9] = parsing[:, 0:2]
    if transfer and "transfer" not in learn:
        out[:, data.TRANSFER] = transfer[0]
    if parsing.shape[1] > 2:
        out[:, HAIR_TARGET:HAIR_TARGET + 1] = parsing[:, 2:3]
    return out


def frozen_modules(model: torch.nn.Module, which: str) -> list:
    """The leaf modules --train-only ``which`` keeps as they are, their parameters set not to
    need gradients."""
    keep = TRAIN_ONLY[which]
    if keep is None:
        return []
    frozen = []
    for name, m in model.named_modules():
        if next(m.children(), None) is not None:
            continue
        if not any(name == p or name.startswith(p + ".") for p in keep):
            m.requires_grad_(False)
            frozen.append(m)
    return frozen


def training_mode(model: torch.nn.Module, frozen: list) -> None:
    """The model in training mode, but the frozen modules in evaluation mode (a batch
    normalisation keeps its running statistics)."""
    model.train()
    for m in frozen:
        m.eval()


@torch.no_grad()
def validate(model: torch.nn.Module, val: dict, inputs: torch.Tensor) -> dict:
    model.eval()
    out = {}
    for i in range(0, len(inputs), 16):
        pred = model(inputs[i:i + 16])
        part = losses(pred, val["target"][i:i + 16], val["fg"][i:i + 16])
        for k, v in part.items():
            out[k] = out.get(k, 0.0) + float(v) * len(pred[0])
    model.train()
    return {k: v / len(inputs) for k, v in out.items()}


def cpu(state: dict) -> dict:
    return {k: v.detach().cpu() for k, v in state.items()}


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=pathlib.Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def train(a) -> pathlib.Path:
    torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    torch.manual_seed(a.seed)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    recipe = {**vars(a), "git_commit": git_commit(), "machine": platform.processor() or platform.machine(),
              "cpus": os.cpu_count(), "render_version": data.renderer_version(),
              "accelerator": (torch.cuda.get_device_name(device) if device.type == "cuda"
                              else None)}
    ds = data.IntrinsicFrames("train", a.res, a.seed, a.cache, sky_flip=a.sky_flip,
                              studio=a.studio, keep_frames=a.preload or not a.workers)
    if a.preload:
        ds.preload()
    recipe["long_hair"] = ds.long_hair
    (out / "recipe.json").write_text(json.dumps(recipe, indent=2))
    vds = data.IntrinsicFrames("val", a.res, 1234, a.val_cache or a.cache)
    val = vds.batch(range(a.val_n))
    vgen = torch.Generator().manual_seed(99)
    val_in = prepare(val, vgen).to(device)
    val = {k: v.to(device) for k, v in val.items()}
    model = IntrinsicNet(a.width, a.transfer, a.hair, a.albedo_head)
    if a.init:
        load_weights(model, torch.load(a.init, map_location="cpu")["state_dict"])
    model.to(device)
    frozen = frozen_modules(model, a.train_only)
    training_mode(model, frozen)
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=a.lr,
                            weight_decay=1e-4)
    ema = EMA(model, a.ema)
    teacher = None
    if a.hold_others:
        if not a.init:
            raise SystemExit("--hold-others holds the buffers to the --init network's own: "
                             "give --init")
        teacher = IntrinsicNet(a.width, a.transfer, a.hair, a.albedo_head)
        load_weights(teacher, torch.load(a.init, map_location="cpu")["state_dict"])
        teacher.to(device).eval().requires_grad_(False)
    feed = batches(ds, a)
    t0 = time.time()
    budget = a.minutes * 60 if a.minutes else None
    step, best, log = 0, math.inf, []
    while True:
        elapsed = time.time() - t0
        frac = elapsed / budget if budget else step / a.steps
        if frac >= 1.0:
            break
        lr = a.lr * (min(1.0, (step + 1) / 200) * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))
        for g in opt.param_groups:
            g["lr"] = lr
        inp, target, fg = (t.to(device, non_blocking=True) for t in next(feed))
        if teacher is not None:
            target = held_target(teacher, inp, target, tuple(a.learn))
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=a.bf16):
            pred = model(inp)
        ls = losses(pred, target, fg, a.face_weight, a.gradient_weight, a.up_weight,
                    a.albedo_weight, a.low_weight, a.low_sigma)
        opt.zero_grad(set_to_none=True)
        ls["total"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        ema.update(model, step)
        step += 1
        if step % a.log_every == 0:
            print(f"step {step} {time.time() - t0:.0f}s lr {lr:.2e} " + " ".join(
                f"{k} {float(v.detach()):.4f}" for k, v in ls.items()), flush=True)
        if step % a.val_every == 0:
            live = {k: v.clone() for k, v in model.state_dict().items()}
            model.load_state_dict(ema.shadow)
            v = validate(model, val, val_in)
            training_mode(model, frozen)
            score = v["normal_deg"] + 10 * v["albedo"] + 10 * v["height"] + 10 * v["transfer"]
            if a.train_only in ("hair", "albedo"):  # the rest is the --init network's
                score = v[a.train_only]
            log.append({"step": step, "seconds": round(time.time() - t0), **v, "score": score})
            print("val", json.dumps(log[-1]), flush=True)
            state = {"state_dict": cpu(ema.shadow), "width": a.width, "step": step, "val": v}
            if score < best:
                best = score
                torch.save(state, out / "best.pt")
            torch.save({**state, "raw_state_dict": cpu(live)}, out / "checkpoint.pt")
            if a.keep_every and step % a.keep_every == 0:
                torch.save(state, out / f"step_{step:06d}.pt")
            model.load_state_dict(live)
            (out / "val.json").write_text(json.dumps(log, indent=1))
    return out


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--width", default="standard", choices=["small", "standard"])
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--cache", help="intrinsic frame cache root (default cache/intrinsic)")
    ap.add_argument("--val-cache", help="the val frames' cache root (default --cache): "
                    "another build's held-out identities, e.g. all with long hair")
    ap.add_argument("--minutes", type=float, help="time box (else --steps)")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--ema", type=float, default=0.998)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu", help="where the network trains (cpu, cuda)")
    ap.add_argument("--workers", type=int, default=0, help="processes making batches ahead of "
                    "the network (0: made inline; each worker reads frames from the disk cache "
                    "rather than keeping them, unless --preload)")
    ap.add_argument("--preload", action="store_true", help="read every training frame into "
                    "memory before training (about 6 MB a frame at 128 px): --workers share them "
                    "rather than each reading the files and computing the targets per sample")
    ap.add_argument("--val-n", type=int, default=48)
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--log-every", type=int, default=50)
    ap.add_argument("--keep-every", type=int, default=0, help="also keep the averaged weights "
                    "every this many steps (step_NNNNNN.pt, at a validation step): val loss on "
                    "synthetic identities is not the only way to choose among them")
    ap.add_argument("--init", help="start from this checkpoint's weights")
    ap.add_argument("--zoom", type=float, default=0.5, help="share of samples zoomed in (ZOOM)")
    ap.add_argument("--cut", type=float, default=0.0, help="share of samples cut by the frame's "
                    "edge (frame_cut)")
    ap.add_argument("--face-weight", type=float, default=0.0, help="face-skin pixels count "
                    "1 + this in the normal loss (model.losses)")
    ap.add_argument("--gradient-weight", type=float, default=0.0, help="weight of the normals' "
                    "neighbour differences in the normal loss (model.normal_gradient)")
    ap.add_argument("--sky-flip", type=float, default=0.0, help="share of training "
                    "environments turned upside down (data.sample_light)")
    ap.add_argument("--studio", type=float, default=0.0, help="share of training lightings "
                    "that are one near-white lamp from the front (data.studio_lamp)")
    ap.add_argument("--bright", type=float, default=0.0, help="share of training crops "
                    "normalised brighter than the product's level, up to BRIGHT_MAX (brighten)")
    ap.add_argument("--up-weight", type=float, default=1.0, help="the normals' up/down "
                    "component's error counts this many times the others' (model.losses)")
    ap.add_argument("--low-weight", type=float, default=0.0, help="weight of the normals' "
                    "Gaussian low band's error in the normal loss (model.normal_low_band)")
    ap.add_argument("--low-sigma", type=float, default=LOW_SIGMA, help="that band's Gaussian, "
                    "pixels at --res")
    ap.add_argument("--albedo-weight", type=float, default=ALBEDO_WEIGHT, help="the albedo "
                    "loss's weight in the total (model.losses)")
    ap.add_argument("--train-only", default="all", choices=sorted(TRAIN_ONLY), help="train "
                    "only these layers (TRAIN_ONLY), the rest kept as --init has them")
    ap.add_argument("--start-step", type=int, default=0, help="batch index to start at (a "
                    "continued run sees new samples)")
    ap.add_argument("--no-bf16", dest="bf16", action="store_false")
    ap.add_argument("--no-transfer", dest="transfer", action="store_false",
                    help="no transfer head (as the networks trained before it)")
    ap.add_argument("--hair", action="store_true", help="a third parsing class, hair "
                    "(model.hair_head); with --train-only hair, only that head trains")
    ap.add_argument("--hold-others", action="store_true", help="every buffer but the albedo "
                    "supervised by the --init network's own prediction, not the light stage's "
                    "(held_target): the albedo trains while the others stay the init's")
    ap.add_argument("--learn", nargs="*", default=[], choices=LEARNABLE, help="with "
                    "--hold-others, these buffers too learn from the light stage")
    ap.add_argument("--albedo-head", action="store_true", help="the albedo's own refining head "
                    "(model.albedo_head); with --train-only albedo, only that head trains")
    return ap


def main(argv=None):
    print(train(parser().parse_args(argv)))


if __name__ == "__main__":
    main()
