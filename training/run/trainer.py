"""One training step (the generator, then the critic) and the training loop of a run: schedule,
validation and the choice of ``best.pt``, logging, checkpoints."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import pathlib
import sys
import time

import torch

from ..data.dataset import make_dataset, renderer_version
from ..model import losses, network
from ..model.checkpoint import save_checkpoint
from .batches import Batches, CachedSamples, downsample_batch
from .ema import WeightAverage
from .lineage import load_init
from .options import net_overrides
from .recipe import git_commit, machine
from .schedule import factor_at, lr_at, parse_stages
from .validation import validate, validation_samples


class Trainer:
    """The optimisers of a run and one step: the generator's objective (the losses ``sw`` keeps
    on), then ``--n-critic`` critic updates while adversarial training is on."""

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
    recipe = {"command": "python -m training.run.train " + " ".join(sys.argv[1:]),
              "args": vars(args), "switches": sw.to_dict(), "net": net.cfg.to_dict(),
              "git_commit": git_commit(), "data_seed": args.seed, "machine": machine(),
              "device": str(device), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "init": init,
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
                save_checkpoint(out / "checkpoint.pt", scored, recipe, step, raw_weights(ema, net))
    recipe["steps"] = step
    recipe["trained_minutes"] = round((time.monotonic() - start) / 60, 2)
    (out / "recipe.json").write_text(json.dumps(recipe, indent=2))
    save_checkpoint(out / "checkpoint.pt", scored, recipe, step, raw_weights(ema, net))
    return out


def raw_weights(ema, net) -> dict:
    """With --ema, checkpoint.pt holds the average (what export and --init read) and, beside it,
    the raw training weights."""
    return {"raw_state_dict": net.state_dict()} if ema else {}
