"""Train one preset of the relighting network on the synthetic light stage.

    python -m training.train --preset draft --minutes 25 --out runs/draft-01

The run folder gets ``recipe.json`` (every argument, git commit, data seed, versions, machine) at
the start, ``log.jsonl`` (losses over time) and ``checkpoint.pt`` (weights + config + recipe);
training/export.py copies the recipe into the model card. Training is time-boxed (``--minutes``)
or step-boxed (``--steps``): the learning-rate schedule, the progressive resolutions and the starts
of adversarial and temporal training are all fractions of that budget. A step budget makes runs
independent of the machine's load (the ablations use it); a time budget fits a run into a slot.

``--measure-speed`` times training steps for fp32 / bf16 autocast / channels-last instead.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import inspect
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

from addon import normalise

from .model import losses, network, warp

VAL_SEED = 777  # val samples (held-out identities) for the curves logged during training
IMAGE_KEYS = ("img_t", "img_t1", "gt_t", "gt_t1")
MASK_KEYS = ("mask_t", "mask_t1", "parsing_t", "parsing_t1")
TRANSPORT_KEYS = ("transport_t", "transport_t1")


# ------------------------------------------------------------------------------------ data to units

def _hwc(img: np.ndarray) -> np.ndarray:
    return np.moveaxis(img, 0, -1) if img.shape[0] == 3 else img


def normalise_sample(sample: dict) -> dict:
    """A light-stage sample (absolute radiance) -> the network's normalised units, exactly as the
    engine will see a clip: one exposure scale s for both frames (one clip), the target light at
    unit power (k), ground truth relit / k, source lights / s. Images stay channels-first.

    Why relit / k and not / (s k): image / s is the scene seen under lights / s (shading is linear
    in the light), so the target light L^k is L^k / s there, and its render is R(L^k / k) * k / s;
    back to absolute (* s) that is R(L^k / k) * k. The decoder sees L^k / k, so its output is
    R(L^k / k) = relit / k, a function of what the network sees. Dividing by s as well made the
    target depend on the absolute source power (unobservable in image / s) and the self-relit
    path (training.model.losses) disagree with the target path by that factor."""
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    s = normalise.exposure_scale([_hwc(f32(sample["img_t_i"])), _hwc(f32(sample["img_t1_j"]))])
    unit_k, k = normalise.normalise_light(f32(sample["light_k"]))
    gain = 1.0 / k if k > 0 else 0.0  # an all-dark target: black ground truth
    out = {
        "img_t": f32(sample["img_t_i"]) / s, "img_t1": f32(sample["img_t1_j"]) / s,
        "gt_t": f32(sample["gt_t_k"]) * gain, "gt_t1": f32(sample["gt_t1_k"]) * gain,
        "light_k": network.to_channels_first(unit_k),
        "src_t": network.to_channels_first(f32(sample["light_i"]) / s),
        "src_t1": network.to_channels_first(f32(sample["light_j"]) / s),
        "scale": np.float32(s), "light_scale": np.float32(k),
    }
    for key in MASK_KEYS + ("flow_fw", "flow_bw", "valid_fw", "valid_bw"):
        out[key] = f32(sample[key])
    for key in TRANSPORT_KEYS:  # light-independent: no normalisation
        if key in sample:
            out[key] = f32(sample[key])
    return out


def relit_to_absolute(relit, scale: float, light_scale: float):
    """The network's relit output -> absolute radiance: the inverse of normalise_sample's target
    (relit / k). ``scale`` (s) is taken for symmetry with the inputs and deliberately unused."""
    del scale
    return relit * light_scale


def collate(samples: list[dict], device="cpu") -> dict:
    return {k: torch.from_numpy(np.stack([s[k] for s in samples])).to(device) for k in samples[0]}


def _min_pool(x, f):
    return -F.max_pool2d(-x, f)


def downsample_batch(b: dict, factor: int) -> dict:
    """The batch at 1/factor resolution (progressive training): area-averaged images and labels,
    flows scaled, validity kept only where every source pixel was valid."""
    if factor == 1:
        return b
    out = dict(b)
    for k in IMAGE_KEYS + MASK_KEYS + tuple(k for k in TRANSPORT_KEYS if k in b):
        out[k] = F.avg_pool2d(b[k], factor)
    for k in ("flow_fw", "flow_bw"):
        out[k] = warp.downsample_flow(b[k], factor)
    for k in ("valid_fw", "valid_bw"):
        out[k] = _min_pool(b[k], factor)
    return out


# ---------------------------------------------------------------------------------------- recipe

def git_commit() -> str:
    root = pathlib.Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "training", "addon"],
                               cwd=root, capture_output=True, text=True).stdout.strip()
        return head + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}


# -------------------------------------------------------------------------------------- schedule

def parse_stages(text: str) -> list[tuple[float, int]]:
    """"0.4:4,0.75:2,1:1" -> [(0.4, 4), (0.75, 2), (1.0, 1)]: down-sampling factor until each
    fraction of the time budget (progressive training, low resolution first)."""
    stages = []
    for part in text.split(","):
        frac, factor = part.split(":")
        stages.append((float(frac), int(factor)))
    if stages[-1][0] < 1.0:
        raise ValueError("the last progressive stage must reach fraction 1")
    return stages


def factor_at(stages, frac: float) -> int:
    for until, factor in stages:
        if frac < until:
            return factor
    return stages[-1][1]


def lr_at(base: float, frac: float, step: int = 0, warmup: int = 0) -> float:
    """Cosine decay over the time budget to 5% of the base rate; with ``warmup`` steps, a linear
    ramp from base / warmup up to the cosine over the first ones (for runs continued with
    ``--init``, which start with fresh optimiser moments and a fresh critic)."""
    cosine = base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(frac, 1.0))))
    return cosine * min(1.0, (step + 1) / warmup) if warmup > 0 else cosine


# ---------------------------------------------------------------------------------------- dataset

def make_dataset(split: str, resolution: int, seed: int, sampling: bool = True, **kwargs):
    """The synthetic light stage (training.data.dataset), with lighting sampling off for that
    ablation."""
    from .data.dataset import LightStageDataset  # lazy: tests use a stand-in dataset

    params = inspect.signature(LightStageDataset).parameters
    if not sampling:
        if "sampling" not in params:
            raise ValueError("this LightStageDataset has no 'sampling' switch; the no_sampling "
                             "ablation needs one")
        kwargs["sampling"] = False
    kwargs = {k: v for k, v in kwargs.items() if k in params}
    return LightStageDataset(split, resolution, seed, **kwargs)


def renderer_version() -> str:
    """training.data.dataset's render version (imported late, like the dataset)."""
    from .data.dataset import renderer_version as version

    return version()


# Samples are costly to render (~0.5 s at 128 px on one core) and a pure function of
# (seed, split, idx), so a renderer process can fill a folder while training reads what is there.
_HALF = ("img_t_i", "img_t1_j", "gt_t_k", "gt_t1_k", "flow_fw", "flow_bw")


def render_cache(folder, split: str, resolution: int, seed: int, start: int, count: int,
                 sampling: bool = True) -> None:
    """Render samples start..start+count-1 into ``folder`` (one .npz each, skipping those there)."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ds = make_dataset(split, resolution, seed, sampling=sampling)
    (folder / "cache.json").write_text(json.dumps(
        {"split": split, "resolution": resolution, "seed": seed, "sampling": sampling,
         "dataset": "training.data.dataset.LightStageDataset", "git_commit": git_commit(),
         "renderer": renderer_version()}, indent=2))
    for idx in range(start, start + count):
        path = folder / f"{idx:07d}.npz"
        if path.exists():
            continue
        s = ds[idx]
        # half floats hold the radiance range here (< 65504) and halve the disk and reads
        s = {k: v.astype(np.float16) if k in _HALF else v for k, v in s.items()}
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **s)
        tmp.rename(path)  # readers never see a half-written file


class CachedSamples:
    """The samples rendered so far into a cache folder (the list is refreshed as it grows)."""

    def __init__(self, folder):
        self.folder = pathlib.Path(folder)
        self.refresh()

    def refresh(self):
        self.files = sorted(p for p in self.folder.glob("*.npz") if not p.name.endswith(".tmp.npz"))
        if not self.files:
            raise FileNotFoundError(f"no rendered samples in {self.folder} yet")

    def __len__(self):
        return len(self.files)

    def __getitem__(self, i):
        with np.load(self.files[i]) as z:
            return {k: z[k].astype(np.float32) for k in z.files}


class Batches:
    """Endless shuffled batches of normalised samples from a map-style dataset."""

    def __init__(self, dataset, batch: int, seed: int, device="cpu"):
        self.ds, self.batch, self.device = dataset, batch, device
        self.rng = np.random.default_rng(seed)
        self.order, self.pos = [], 0

    def __next__(self) -> dict:
        picks = []
        while len(picks) < self.batch:
            if self.pos >= len(self.order):
                if hasattr(self.ds, "refresh"):
                    self.ds.refresh()
                self.order, self.pos = self.rng.permutation(len(self.ds)), 0
            picks.append(normalise_sample(self.ds[int(self.order[self.pos])]))
            self.pos += 1
        return collate(picks, self.device)


# ----------------------------------------------------------------------------------------- steps

class Trainer:
    def __init__(self, net, sw: losses.Switches, args, device="cpu"):
        self.net, self.sw, self.args, self.device = net, sw, args, device
        if args.optim == "rmsprop":  # the paper: RMSprop 5e-5 for every network
            self.opt = torch.optim.RMSprop(net.parameters(), lr=args.lr)
        else:
            self.opt = torch.optim.Adam(net.parameters(), lr=args.lr)
        self.critic = losses.Critic(args.critic_width).to(device) if sw.adversarial else None
        self.opt_d = losses.make_critic_optimizer(self.critic) if self.critic else None
        if args.channels_last:
            self.net.to(memory_format=torch.channels_last)
            if self.critic:
                self.critic.to(memory_format=torch.channels_last)

    def autocast(self):
        if self.args.bf16:
            return torch.autocast(device_type=self.device.type if hasattr(self.device, "type")
                                  else str(self.device), dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def _layout(self, b):
        if not self.args.channels_last:
            return b
        return {k: v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 else v
                for k, v in b.items()}

    def step(self, b: dict, lr: float, adv_on: bool, temporal_on: bool = True) -> dict:
        b = self._layout(b)
        for g in self.opt.param_groups:
            g["lr"] = lr
        use_adv = adv_on and self.critic is not None
        sw = self.sw if temporal_on else dataclasses.replace(self.sw, temporal=False)
        with self.autocast():
            total, parts, fake = losses.generator_objective(
                self.net, b, sw, self.critic if use_adv else None)
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(self.net.parameters(), 5.0)
        self.opt.step()
        if use_adv:
            for _ in range(self.args.n_critic):
                with self.autocast():
                    d = losses.critic_loss(self.critic, b["img_t"], b["gt_t"], fake, b["light_k"])
                self.opt_d.zero_grad(set_to_none=True)
                d.backward()
                self.opt_d.step()
                self.critic.clip_weights(0.01)
            parts["critic"] = float(d.detach())
        parts["total"] = float(total.detach())
        return parts


class WeightAverage:
    """An exponential moving average of the generator's weights (``--ema DECAY``): with batch 8 the
    weights after any one step carry that step's noise, and a val-selected checkpoint picks the
    luckiest of them (the "dip" of continued runs, models/README.md). The average is what gets
    validated, chosen as ``best.pt`` and exported; the raw weights keep training. Early in a run
    from scratch the decay is held at (1 + n) / (10 + n) so the average is not dominated by the
    random start; a run from ``--init`` starts its average at the loaded weights."""

    def __init__(self, net, decay: float, warm: bool):
        self.decay, self.warm, self.updates = float(decay), warm, 0
        self.net = copy.deepcopy(net).eval()
        for p in self.net.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, net):
        self.updates += 1
        d = self.decay if self.warm else min(self.decay, (1 + self.updates) / (10 + self.updates))
        for a, b in zip(self.net.parameters(), net.parameters()):
            a.lerp_(b.detach(), 1.0 - d)
        for a, b in zip(self.net.buffers(), net.buffers()):
            a.copy_(b)


def net_overrides(args) -> dict:
    """Width / depth overrides of the preset (the extra points of the accuracy/time frontier)."""
    out = {}
    for key in ("widths", "blocks"):
        text = getattr(args, key, None)
        if text:
            vals = tuple(int(v) for v in text.split(","))
            if len(vals) != 4 or min(vals) < 1:
                raise SystemExit(f"--{key} takes four positive integers, e.g. 16,24,48,64")
            out[key] = vals
    return out


def load_init(net, path) -> dict:
    """Start from a checkpoint's weights (continue or fine-tune a run; the schedule starts anew).
    The architecture must be the same: another preset or width is a clear error."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    if ck.get("config") != net.cfg.to_dict():
        raise SystemExit(f"--init {path}: its network ({ck.get('config')}) is not the one this run "
                         f"builds ({net.cfg.to_dict()}); use the same --preset/--widths/--blocks.")
    net.load_state_dict(ck["state_dict"])
    recipe = ck.get("recipe") or {}
    return {"checkpoint": str(path), "step": ck.get("step"), "recipe": recipe.get("command"),
            "render_version": samples_version(recipe), "git_commit": recipe.get("git_commit"),
            "init": resolve_lineage(recipe.get("init"))}


def samples_version(recipe: dict) -> str:
    """The light stage render version a run's samples had (training.data.dataset.RENDER_VERSION).
    Runs recorded before the field was kept all trained on v1 samples: v2 came with it."""
    return recipe.get("render_version") or "v1"


def resolve_lineage(init: dict | None) -> dict | None:
    """The whole chain of runs a checkpoint was trained from: ``init`` (the recipe's record of the
    checkpoint a run started from) with that checkpoint's own ``init`` nested in it, and so on back
    to a run from scratch, so a model trained further several times can be reproduced from its
    card alone. Records written before the chain was kept (one level) are completed from the
    parent checkpoints where they are on disk; where one is not, the chain stops there."""
    if not init or "init" in init:
        return init
    path = pathlib.Path(init.get("checkpoint") or "")
    if not path.is_file():
        return init
    parent = (torch.load(path, map_location="cpu", weights_only=False).get("recipe") or {})
    return {**init, "init": resolve_lineage(parent.get("init"))}


def save_checkpoint(path, net, recipe, step, extra=None):
    torch.save({"state_dict": net.state_dict(), "config": net.cfg.to_dict(), "recipe": recipe,
                "step": step, **(extra or {})}, path)


def load_checkpoint(path, map_location="cpu", raw: bool = False):
    """A checkpoint's network (eval mode) and the checkpoint. ``raw``: the raw training weights
    that a run with --ema keeps beside the average in checkpoint.pt, instead of the average."""
    ck = torch.load(path, map_location=map_location, weights_only=False)
    cfg = network.NetConfig(**{k: tuple(v) if isinstance(v, list) else v
                               for k, v in ck["config"].items()})
    net = network.RelightNet(cfg)
    if raw and "raw_state_dict" not in ck:
        raise SystemExit(f"{path} holds one set of weights (no --ema average): leave out --raw")
    net.load_state_dict(ck["raw_state_dict"] if raw else ck["state_dict"])
    return net.eval(), ck


def train(args) -> pathlib.Path:
    if args.cache and args.backdrops != "wall":
        raise SystemExit("--backdrops works with --data-cache or on-the-fly samples, not with "
                         "--cache (those samples are rendered already)")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)
    device = torch.device("cuda" if torch.cuda.is_available() and not args.cpu else "cpu")
    if device.type == "cpu" and args.threads:
        torch.set_num_threads(args.threads)
    sw = losses.Switches.ablation(args.ablation)
    if args.transport_loss:
        sw = dataclasses.replace(sw, transport=True)
    net = network.build(args.preset, **net_overrides(args))
    init = load_init(net, args.init) if args.init else None
    net = net.to(device)
    # pre-rendered samples (--cache) keep the render version they were made with
    rendered = (json.loads((pathlib.Path(args.cache) / "cache.json").read_text())
                if args.cache else None)
    recipe = {"command": "python -m training.train " + " ".join(sys.argv[1:]), "args": vars(args),
              "switches": sw.to_dict(), "net": net.cfg.to_dict(), "git_commit": git_commit(),
              "data_seed": args.seed, "machine": machine(), "device": str(device),
              "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "init": init,
              "render_version": (rendered.get("renderer", "v1") if rendered
                                 else renderer_version())}
    (out / "recipe.json").write_text(json.dumps(recipe, indent=2))
    if args.cache:
        ds = CachedSamples(args.cache)
        recipe["data_cache"] = rendered
    elif args.data_cache:
        ds = make_dataset("train", args.resolution, args.seed, sampling=sw.sampling,
                          cache_dir=args.data_cache, transport=sw.transport,
                          backdrops=args.backdrops)
        recipe["data_cache"] = {"dir": str(args.data_cache), "pool": ds.pool}
    else:
        ds = make_dataset("train", args.resolution, args.seed, sampling=sw.sampling,
                          transport=sw.transport, backdrops=args.backdrops)
    if args.overfit:  # a sanity check: can the model fit a few samples far below the baselines?
        ds = [ds[i] for i in range(args.overfit)]
        val = ds
    else:
        val = validation_samples(args.resolution, args.val_n)
    batches = Batches(ds, args.batch, args.seed, device)
    trainer = Trainer(net, sw, args, device)
    ema = WeightAverage(net, args.ema, warm=init is not None) if args.ema else None
    scored = ema.net if ema else net  # the weights validated, chosen and exported
    stages = parse_stages(args.progressive)
    budget, start, step = args.minutes * 60.0, time.monotonic(), 0
    next_val, best = 0.0, math.inf
    with open(out / "log.jsonl", "w") as log:
        while True:
            if args.steps:  # a step budget: the schedule no longer depends on the machine's load
                frac = step / args.steps
                val_due = step >= next_val
            else:
                frac = (time.monotonic() - start) / budget
                val_due = time.monotonic() - start >= next_val
            done = frac >= 1.0 or (args.max_steps and step >= args.max_steps)
            if val and (done or val_due):
                row = {"val": validate(scored, val), "step": step,
                       "minutes": round((time.monotonic() - start) / 60, 2)}
                if row["val"]["model"]["rmse"] < best:  # chosen on val, never on the test set
                    best = row["val"]["model"]["rmse"]
                    save_checkpoint(out / "best.pt", scored, recipe, step, {"val": row["val"]})
                log.write(json.dumps(row) + "\n")
                log.flush()
                print(json.dumps(row), flush=True)
                next_val += args.val_every_steps if args.steps else args.val_every * 60.0
            if done:
                break
            b = downsample_batch(next(batches), factor_at(stages, frac))
            parts = trainer.step(b, lr_at(args.lr, frac, step, args.warmup_steps),
                                 adv_on=frac >= args.adv_start,
                                 temporal_on=frac >= args.temporal_start)
            if ema:
                ema.update(net)
            step += 1
            if step % args.log_every == 0 or step == 1:
                parts.update(step=step, minutes=round((time.monotonic() - start) / 60, 2),
                             size=int(b["img_t"].shape[-1]))
                log.write(json.dumps(parts) + "\n")
                log.flush()
                print(json.dumps(parts), flush=True)
            if step % args.save_every == 0:
                save_checkpoint(out / "checkpoint.pt", scored, recipe, step, _raw(ema, net))
    recipe["steps"] = step
    recipe["trained_minutes"] = round((time.monotonic() - start) / 60, 2)
    (out / "recipe.json").write_text(json.dumps(recipe, indent=2))
    save_checkpoint(out / "checkpoint.pt", scored, recipe, step, _raw(ema, net))
    return out


def _raw(ema, net) -> dict:
    """With --ema, checkpoint.pt holds the average (what export and --init read) and, beside it,
    the raw training weights."""
    return {"raw_state_dict": net.state_dict()} if ema else {}


# ------------------------------------------------------------------------------------ validation

def validation_samples(resolution: int, n: int) -> list:
    """The first n samples of the val split (held-out identities, rendered once, kept in memory)."""
    if n <= 0:
        return []
    ds = make_dataset("val", resolution, VAL_SEED)
    return [ds[i] for i in range(n)]


def validate(net, samples) -> dict:
    """Val RMSE / PSNR / SSIM of the model and both baselines (training.evaluate's metrics)."""
    from . import evaluate

    was_training = net.training
    net.eval()
    try:
        res = evaluate.evaluate(evaluate.torch_predictor(net), samples)
    finally:
        net.train(was_training)
    return {name: {k: round(v, 4) for k, v in res[name].items()}
            for name in ("model", "identity", "irradiance_ratio")}


def curve(run) -> str:
    """A run's log as a markdown table: val metrics of the model and both baselines over time,
    the model's shading correlation, and the mean training loss terms since the previous val row
    ("-" for a term the run did not train)."""
    rows = [json.loads(line) for line in open(pathlib.Path(run) / "log.jsonl")]
    terms = ("basic", "latent", "parsing", "temporal", "transport", "adv")
    out = ["| step | min | model RMSE / PSNR / SSIM | shading corr | identity | irradiance ratio | "
           + " | ".join(terms) + " |", "|" + "---|" * (6 + len(terms))]
    pending = []
    for r in rows:
        if "val" not in r:
            pending.append(r)
            continue
        v = r["val"]
        cell = lambda m: f"{m['rmse']:.4f} / {m['psnr']:.2f} / {m['ssim']:.3f}"  # noqa: E731
        means = [f"{np.mean([p[k] for p in pending if k in p]):.3f}"
                 if any(k in p for p in pending) else "-" for k in terms]
        corr = v["model"].get("shading_corr")
        out.append(f"| {r['step']} | {r['minutes']} | {cell(v['model'])} | "
                   f"{'-' if corr is None else f'{corr:.3f}'} | {cell(v['identity'])} | "
                   f"{cell(v['irradiance_ratio'])} | " + " | ".join(means) + " |")
        pending = []
    return "\n".join(out)


# ------------------------------------------------------------------------------ speed measurement

def measure_speed(args, batch_fn) -> list[dict]:
    """Training steps per second for fp32 / bf16 / channels-last on this machine."""
    rows = []
    for bf16, cl in ((False, False), (True, False), (False, True), (True, True)):
        torch.manual_seed(0)
        a = argparse.Namespace(**{**vars(args), "bf16": bf16, "channels_last": cl})
        trainer = Trainer(network.build(args.preset), losses.Switches(), a)
        b = batch_fn()
        trainer.step(b, args.lr, adv_on=True)  # warm-up
        t0 = time.perf_counter()
        for _ in range(args.speed_steps):
            trainer.step(b, args.lr, adv_on=True)
        dt = (time.perf_counter() - t0) / args.speed_steps
        rows.append({"bf16": bf16, "channels_last": cl, "s_per_step": round(dt, 3),
                     "pairs_per_s": round(args.batch / dt, 2)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="standard", choices=sorted(network.PRESETS))
    p.add_argument("--minutes", type=float, default=100.0, help="wall-clock training budget")
    p.add_argument("--max-steps", type=int, default=0, help="stop early after this many steps")
    p.add_argument("--steps", type=int, default=0,
                   help="a step budget instead of --minutes: the learning-rate schedule, "
                        "progressive stages and the adversarial/temporal starts become fractions "
                        "of it, so runs compare fairly on a loaded machine (ablations)")
    p.add_argument("--val-every-steps", type=int, default=250,
                   help="steps between val metrics when --steps is given")
    p.add_argument("--init", metavar="CKPT",
                   help="start from this checkpoint's weights (same architecture), e.g. to train "
                        "a shipped model further: runs/final-t2500/checkpoint.pt. The schedule "
                        "starts anew: continue with a lower --lr and --progressive 1:1 (a 1e-3 "
                        "restart at 64 px undid a trained Draft within two steps)")
    p.add_argument("--widths", help="override the preset's four encoder widths, e.g. 12,16,32,48")
    p.add_argument("--blocks", help="override the preset's four block counts, e.g. 1,1,1,1")
    p.add_argument("--out", default="runs/latest")
    p.add_argument("--ablation", default="full",
                   choices=["full", "no_structure", "no_temporal", "no_parsing", "no_sampling",
                            "basic_only"])
    p.add_argument("--transport-loss", action="store_true",
                   help="supervise the ratio head's SH transport with the light stage's (not in "
                        "the paper; an experiment)")
    p.add_argument("--backdrops", default="wall", choices=["wall", "varied"],
                   help="what stands behind the training subjects: the stage's smooth wall, or "
                        "photos, chroma-key screens and busy patterns as well "
                        "(training/lightstage/backdrops.py); validation keeps the wall")
    p.add_argument("--resolution", type=int, default=128, help="light-stage render size")
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seed", type=int, default=0, help="torch and data seed")
    p.add_argument("--optim", default="adam", choices=["adam", "rmsprop"],
                   help="network optimiser; the paper's is rmsprop at 5e-5 (the critic always is)")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="validate, choose best.pt and export an exponential moving average of "
                        "the weights with this decay per step (e.g. 0.999); 0: the raw weights")
    p.add_argument("--warmup-steps", type=int, default=0,
                   help="ramp the learning rate up linearly over these first steps (for runs "
                        "continued with --init, whose optimiser starts afresh)")
    p.add_argument("--progressive", default="0.3:2,1:1",
                   help="fraction:downsample stages (low resolution first)")
    p.add_argument("--adv-start", type=float, default=0.3,
                   help="fraction of the budget after which adversarial training starts")
    p.add_argument("--temporal-start", type=float, default=0.5,
                   help="fraction of the budget after which the temporal term is on: from the "
                        "start it drove the first Draft to a blurred, input-independent output "
                        "(a smooth image is temporally consistent) before it learnt to relight")
    p.add_argument("--n-critic", type=int, default=1)
    p.add_argument("--critic-width", type=int, default=32)
    p.add_argument("--bf16", action="store_true", help="bf16 autocast")
    p.add_argument("--channels-last", action="store_true")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--cpu", action="store_true", help="ignore a GPU")
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--save-every", type=int, default=200)
    p.add_argument("--cache", help="read rendered samples from this folder (see --render)")
    p.add_argument("--data-cache", metavar="DIR",
                   help="light-stage pair cache root (python -m training.data.build_cache), e.g. "
                        "cache/lightstage: about 50x faster than rendering")
    p.add_argument("--overfit", type=int, default=0, metavar="N",
                   help="train on the first N samples only and report metrics on them")
    p.add_argument("--val-n", type=int, default=16, help="val samples for the logged curves")
    p.add_argument("--val-every", type=float, default=5.0, help="minutes between val metrics")
    p.add_argument("--render", metavar="FOLDER",
                   help="render training samples into FOLDER instead of training")
    p.add_argument("--start", type=int, default=0, help="first sample index for --render")
    p.add_argument("--count", type=int, default=1000, help="samples for --render")
    p.add_argument("--curve", metavar="RUN",
                   help="print a run's val curve (model vs baselines) and loss terms, then exit")
    p.add_argument("--measure-speed", action="store_true")
    p.add_argument("--speed-steps", type=int, default=5)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.curve:
        print(curve(args.curve))
        return
    if args.render:
        torch.set_num_threads(args.threads)
        render_cache(args.render, "train", args.resolution, args.seed, args.start, args.count,
                     sampling=losses.Switches.ablation(args.ablation).sampling)
        return
    if args.measure_speed:
        torch.set_num_threads(args.threads)
        ds = make_dataset("train", args.resolution, args.seed)
        batches = Batches(ds, args.batch, args.seed)
        b = next(batches)
        measure_speed(args, lambda: b)
        return
    print(f"run folder: {train(args)}")


if __name__ == "__main__":
    main()
