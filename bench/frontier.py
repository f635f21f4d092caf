"""Accuracy against time: every knob that trades one for the other, measured on the same held-out
test set (the light stage's 'test' split: identities never seen in training), with its Pareto
frontier.

    .venv/bin/python -m bench.frontier                 # full run (models/, ~10-20 min here)
    .venv/bin/python -m bench.frontier --quick         # tiny test set, few repeats (CI)
    .venv/bin/python -m bench.frontier --write-cards   # also record each card's frontier point

Knob groups, each with its own error measure (so each has its own frontier):
* network: the per-frame path of addon/pipeline.py (shrink -> network -> guided coefficients ->
  full-resolution finish; decoding and writing excluded) against the light stage's ground truth,
  RMSE on the portrait region as training/eval/evaluate.py defines it. Knobs: the shipped presets
  (models/*.onnx); width and depth trained at an equal step budget (--research, default
  models/research/: ablation-full, width-narrow, width-deep, each at its working size, its row
  naming widths, blocks, GFLOP, parameters and training steps; absent files are skipped); extra
  widths and depths exported untrained from training/model/network.py, only for configs with no
  trained model here (time only: their accuracy is not measured and is labelled so), working
  resolution (256, 384, 512, full), the full-resolution detail transfer on/off, precision (fp32,
  int8 made with onnxruntime.quantization; fp16 made with onnxruntime.transformers.float16, which
  the CPU provider runs) and execution provider (CPU; GPU providers where present).
* light stage: the selective-effects shortcut against the full 114-light sum
  (bench/lightstage_throughput.py), relative RMSE of the radiance.
* lighting conversion: an HDRI down-sampled at several working widths against the Cycles referee
  (bench/light_conversion.py), relative RMSE on a diffuse sphere; time per conversion.

Timings are medians over repeated runs with the 10th-90th percentile spread, on the machine that
each output names (platform, CPU model, cores, load average, date). The settings compared are
timed together: a few warm-up runs of each, then round-robin rounds (every setting once per round,
the order shuffled with a fixed seed), so start-up costs and load drifts do not fall on the setting
measured first (one run showed an untrained Draft slower than the untrained Final).

Writes frontier.md, .json and .png into --out (bench/results); with --write-cards it adds a "frontier" entry to each measured
model card in --models (the research cards are left as they are).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(ROOT))

from addon import colour, contract, detail, engine, normalise, pipeline  # noqa: E402
from addon.frames import write_atomic  # noqa: E402
from training.eval import report  # noqa: E402
from training.eval.report import machine, machine_line  # noqa: E402

FULL_SIZES = (256, 384, 512)  # plus "full": the test set's own resolution
LINEAR = colour.lookup("Linear Rec.709")
CPU = "CPUExecutionProvider"


# ---- machine and timing -------------------------------------------------------------------

QUIET_LOAD = 2.5  # above this 1-minute load average (2 cores) timings are noisy


def spread(times_s) -> dict:
    """Median and 10th-90th percentiles in milliseconds."""
    t = np.asarray(times_s, np.float64) * 1e3
    return {"ms": float(np.median(t)), "p10": float(np.percentile(t, 10)),
            "p90": float(np.percentile(t, 90)), "runs": int(t.size)}


def interleaved_times(fns, repeats: int, warmup: int = 3, seed: int = 0,
                      rewarm: bool = True) -> list[dict]:
    """Median and spread of each ``fn(round)``, timed round-robin: ``warmup`` untimed rounds,
    then ``repeats`` rounds that each run every fn once, in an order shuffled with a fixed seed.
    Timed one after the other, the first variant paid the thread spin-up, page faults and cold
    caches (an untrained Draft once measured slower than the untrained Final); interleaved, every
    variant's runs spread over the whole session and share its drifts in load. ``rewarm``: each
    timed run follows an untimed run of the same fn, so it finds its weights in the caches as it
    would frame after frame in a real run (round-robin alone timed every run cold: medians up by
    a third and p90 up to twice the median)."""
    rng = np.random.default_rng(seed)
    times = [[] for _ in fns]
    for r in range(-warmup, repeats):
        for i in rng.permutation(len(fns)):
            if rewarm and r >= 0:
                fns[i](r)
            t0 = time.perf_counter()
            fns[i](r)
            if r >= 0:
                times[i].append(time.perf_counter() - t0)
    return [spread(t) for t in times]


@dataclass
class Row:
    group: str            # 'network' | 'light stage' | 'lighting conversion' | 'reference'
    kind: str             # which knob this row varies (colour in the plot)
    label: str
    error: float | None   # the group's error measure; None: not measured (untrained)
    ms: float | None
    p10: float | None = None
    p90: float | None = None
    runs: int = 0
    settings: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    note: str = ""
    frontier: bool = False


# ---- the held-out test set ----------------------------------------------------------------

KEYS = ("img_t_i", "img_t1_j", "gt_t_k", "mask_t", "light_i", "light_k")


def _lightstage_version() -> str:
    """A hash of the light stage's sources: a cached test set is stale when they change."""
    h = hashlib.sha256()
    data = ROOT / "training" / "data"
    for p in sorted((ROOT / "training" / "lightstage").rglob("*.py")) + [
            data / "dataset.py", data / "lighting_sampling.py"]:
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def default_cache() -> pathlib.Path:
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "portrait-relight" / "frontier"


def heldout_samples(resolution: int, n: int, seed: int, cache: pathlib.Path | None):
    """(samples, description): the first ``n`` samples of the held-out 'test' split at
    ``resolution``. With the default seed this is training/data/make_testset.py's fixed test set
    (built once, cached, identified by its sha256); otherwise rendered here (cached too)."""
    try:
        from training.data import make_testset
    except ImportError:
        make_testset = None
    if make_testset is not None and seed == make_testset.TEST_SEED:
        folder = cache / "testset" if cache is not None else None
        arrays = make_testset.load_testset(resolution, n, folder)
        meta = make_testset.testset_path(resolution, n, folder).with_suffix(".json")
        sha = json.loads(meta.read_text())["sha256"][:16] if meta.is_file() else "?"
        samples = [{k: arrays[k][i] for k in KEYS} for i in range(n)]
        return samples, (f"training/data/make_testset.py: light stage 'test' split (held-out "
                         f"identities), seed {seed}, {n} samples at {resolution}x{resolution}, "
                         f"sha256 {sha}...")
    return _rendered(resolution, n, seed, cache), (
        f"light stage 'test' split (held-out identities), seed {seed}, {n} samples at "
        f"{resolution}x{resolution}")


def _rendered(resolution: int, n: int, seed: int, cache: pathlib.Path | None) -> list[dict]:
    from training.data.dataset import LightStageDataset

    folder = None
    if cache is not None:
        folder = cache / f"test-{resolution}-{seed}-{_lightstage_version()}"
        folder.mkdir(parents=True, exist_ok=True)
    ds, out = None, []
    for idx in range(n):
        path = folder / f"{idx:04d}.npz" if folder else None
        if path is not None and path.is_file():
            with np.load(path) as z:
                out.append({k: z[k] for k in KEYS})
            continue
        ds = ds or LightStageDataset("test", resolution, seed=seed, length=n)
        s = ds[idx]
        out.append({k: np.asarray(s[k], np.float32) for k in KEYS})
        if path is not None:
            def write(tmp, arrays=out[-1]):
                with open(tmp, "wb") as f:  # a file, so np.savez adds no .npz to the name
                    np.savez(f, **arrays)
            write_atomic(path, write)
    return out


# ---- the network group --------------------------------------------------------------------

@dataclass
class Frame:
    x_full: np.ndarray    # (3, H, W) exposure-normalised linear input
    x_max: float
    scale: float          # s
    light: np.ndarray     # the target light L^k (absolute)
    gt: np.ndarray        # (3, H, W) absolute ground truth
    mask: np.ndarray      # (H, W) bool portrait region


def frames_of(samples) -> list[Frame]:
    out = []
    for s in samples:
        hwc = [np.moveaxis(s[k], 0, -1) for k in ("img_t_i", "img_t1_j")]
        scale = normalise.exposure_scale(hwc)  # one scale for the two frames, as in training
        x = np.ascontiguousarray(s["img_t_i"] / np.float32(scale), dtype=np.float32)
        out.append(Frame(x, float(x.max()), scale, s["light_k"], s["gt_t_k"],
                         s["mask_t"][0] > 0.5))
    return out


def card_for(onnx_path, stride: int, working: int, name: str, preset: str,
             classes) -> engine.ModelCard:
    """A card in memory for a variant made here (untrained export, int8, fp16), never written."""
    p = pathlib.Path(onnx_path)
    return engine.ModelCard(p.with_suffix(".json"), p, name, preset, contract.CONTRACT_VERSION,
                            "", stride, working, tuple(classes), {})


def open_session(card: engine.ModelCard, threads: int, provider: str):
    import onnxruntime as ort

    so = engine.session_options(ort, threads)
    sess = ort.InferenceSession(str(card.onnx_path), so, providers=[provider])
    return engine.RelightSession(sess, card, sess.get_providers())


def relight_frame(session, f: Frame, working: int, detail_on: bool,
                  fullres: detail.FullRes) -> np.ndarray:
    """The pipeline's per-frame stages (addon/pipeline.py) -> half (3, H, W) absolute radiance."""
    h, w = f.x_full.shape[1:]
    plan = pipeline.Plan(LINEAR, f.scale, (w, h), detail.working_shape(h, w, working),
                         detail_on, False, "none")
    x_low = pipeline.shrink_planar(f.x_full, plan, fullres)
    relit_low, _, _, k = pipeline.infer_planar(session, x_low, f.light)
    ab = pipeline.coefficients_planar(x_low, relit_low, k, plan, fullres)
    return pipeline.finish_planar(f.x_full, ab, f.x_max, fullres)[0]


@dataclass
class Variant:
    """One network setting to measure: how to run a frame, and the fields of its row."""
    kind: str
    label: str
    session: object
    working: int
    detail: bool
    settings: dict
    note: str = ""
    accuracy: bool = True  # False: an untrained export, timed only
    extra: dict = field(default_factory=dict)

    def run(self, frame: Frame, fullres) -> np.ndarray:
        return relight_frame(self.session, frame, self.working, self.detail, fullres)


def accuracy_of(v: Variant, frames, fullres) -> dict:
    """Mean held-out RMSE / PSNR / SSIM on the portrait region (training/eval/evaluate.py)."""
    from training.eval import metrics

    m = [metrics.image_metrics(v.run(f, fullres).astype(np.float32), f.gt, f.mask)
         for f in frames]
    return {k: float(np.mean([x[k] for x in m])) for k in m[0]}


def measure_variants(variants: list[Variant], frames, fullres, args, log) -> list[dict]:
    """Accuracy of each variant, then the time of all of them interleaved (interleaved_times);
    round r relights test frame r for every variant, so all time the same frames."""
    results = []
    for v in variants:
        if v.accuracy:
            log(f"accuracy: {v.kind}: {v.label}")
        results.append(accuracy_of(v, frames, fullres) if v.accuracy else {})
    log(f"timing {len(variants)} network settings round-robin ({args.warmup} warm-up + "
        f"{args.repeats} rounds)")
    fns = [lambda r, v=v: v.run(frames[r % len(frames)], fullres) for v in variants]
    for res, t in zip(results, interleaved_times(fns, args.repeats, args.warmup)):
        res.update(t)
    return results


def network_row(v: Variant, result: dict) -> Row:
    return Row("network", v.kind, v.label, result.get("rmse"), result["ms"], result["p10"],
               result["p90"], result["runs"], v.settings,
               {**v.extra, **{k: result[k] for k in ("psnr", "ssim") if k in result}}, v.note)


def shipped_models(models_dir: pathlib.Path, names=None, log=None) -> list[engine.ModelCard]:
    """Checked cards of ``models_dir``'s *.onnx (or of ``names`` there: stems); a missing or
    broken one is reported and left out, never measured."""
    folder = pathlib.Path(models_dir)
    paths = sorted(folder.glob("*.onnx")) if names is None else [folder / f"{n}.onnx"
                                                                   for n in names]
    log = log or (lambda msg: print(msg, file=sys.stderr))
    cards = []
    for p in paths:
        try:
            card = engine.load_card(p)
            engine.verify_checksum(card)
            if card.contract == contract.INTRINSIC_CONTRACT:
                log(f"skipping {p.name}: an intrinsic preset (bench.intrinsic_speed and "
                    "bench.intrinsic_effects measure it)")
                continue
            cards.append(card)
        except Exception as err:  # noqa: BLE001  a broken card is reported, not measured
            log(f"skipping {p.name}: {err}")
    return cards


def config_of(card: engine.ModelCard) -> dict | None:
    """The network config (widths, blocks...) the card was exported from, if it says."""
    data = card.data
    arch = data.get("architecture") if isinstance(data.get("architecture"), dict) else {}
    training = data.get("training") if isinstance(data.get("training"), dict) else {}
    return arch.get("config") or (training.get("recipe") or {}).get("net")


def training_steps(card: engine.ModelCard) -> dict:
    """How long the card's network trained, from its recipe (training/run/train.py): the step budget
    (--steps; None for a run boxed in minutes), the steps run, and the exported checkpoint's
    step (best.pt is the best on val, which may come before the end)."""
    training = card.data.get("training") if isinstance(card.data.get("training"), dict) else {}
    recipe = training.get("recipe") or {}
    args, ck = recipe.get("args") or {}, recipe.get("exported_checkpoint") or {}
    return {"step_budget": args.get("steps") or None,
            "minutes_budget": None if args.get("steps") else args.get("minutes"),
            "steps_run": recipe.get("steps"), "checkpoint": ck.get("file"),
            "checkpoint_step": ck.get("step"), "ablation": args.get("ablation")}


@dataclass
class Context:
    """What the network group's builders share: arguments, full size, sizes, scratch folder."""
    args: argparse.Namespace
    res: int
    sizes: list
    folder: pathlib.Path
    fullres: object
    log: object

    def settings(self, card, ws, det, precision="fp32", prov=CPU) -> dict:
        return {"model": card.name, "preset": card.preset, "working": ws, "full": self.res,
                "detail": det, "precision": precision, "provider": prov,
                "threads": self.args.threads}

    def name(self, card, ws, precision="fp32") -> str:
        return f"{card.preset} {precision} {ws if ws < self.res else 'full'}"

    def cost(self, config: dict | None, ws: int, stride: int) -> dict:
        """GFLOP per frame at the working shape of the test frames padded to the stride (as the
        engine runs it), and parameters, of a network config; {} where the card has none."""
        from training.model import network

        try:
            net = network.RelightNet(network.NetConfig(**{
                k: tuple(v) if isinstance(v, list) else v for k, v in (config or {}).items()}))
        except (TypeError, ValueError) as err:  # no config, or one this code does not know
            self.log(f"no cost for config {config}: {err}")
            return {}
        h, w = (-(-n // stride) * stride for n in detail.working_shape(self.res, self.res, ws))
        return {"gflop_at_working": round(network.count_flops(net, h, w) / 1e9, 4),
                "parameters": network.parameter_count(net)}


RESEARCH_POINTS = ("ablation-full", "width-narrow", "width-deep")
TRAINED_KIND = "width/depth (trained, equal steps)"


def research_variants(ctx: Context, skipped: list) -> list[Variant]:
    """The width/depth networks trained at an equal step budget (models/research/, exported by
    training/run/export.py), each at its working size like the shipped presets. Missing files are
    logged and left out; with none, the group is absent."""
    args, log = ctx.args, ctx.log
    if "research" in args.skip:
        return []
    missing = [n for n in RESEARCH_POINTS if not (args.research / f"{n}.onnx").is_file()]
    if missing:
        log(f"research models missing in {args.research}: {', '.join(missing)}")
        skipped.append(f"trained width/depth point(s) {', '.join(missing)} "
                       f"(not in {args.research})")
    present = [n for n in RESEARCH_POINTS if n not in missing]
    cards = shipped_models(args.research, present, log)
    broken = [n for n in present if n not in {c.onnx_path.stem for c in cards}]
    if broken:
        skipped.append(f"trained width/depth point(s) {', '.join(broken)} (model or card "
                       "unusable: see the log)")
    steps = [training_steps(c) for c in cards]
    budgets = {s["step_budget"] for s in steps}
    kind = TRAINED_KIND if len(budgets) == 1 and None not in budgets else "width/depth (trained)"
    if cards and kind != TRAINED_KIND:
        log(f"research models: step budgets {sorted(budgets, key=str)}: not an equal-step set")
    out = []
    for card, st in zip(cards, steps):
        ws, config = min(card.working_size, ctx.res), config_of(card)
        settings = {**ctx.settings(card, ws, True), "widths": (config or {}).get("widths"),
                    "blocks": (config or {}).get("blocks"),
                    **ctx.cost(config, ws, card.stride), "training": st, "config": config}
        out.append(Variant(kind, f"{card.name} fp32 {ws if ws < ctx.res else 'full'}",
                           open_session(card, args.threads, CPU), ws, True, settings,
                           research_note(settings)))
    return out


def research_note(s: dict) -> str:
    """The config and training of a trained width/depth point, for the table's note column."""
    def join(v):
        return ",".join(map(str, v)) if v else "?"

    t = s["training"]
    trained = (f"{t['step_budget']} steps" if t["step_budget"] else
               f"{t['minutes_budget']} min" if t["minutes_budget"] else "training not recorded")
    if t["checkpoint_step"] is not None:
        trained += f" ({t['checkpoint'] or 'checkpoint'} at step {t['checkpoint_step']})"
    cost = (f"; {s['gflop_at_working']} GFLOP at {s['working']}, {s['parameters']:,} parameters"
            if "parameters" in s else "")
    return f"widths {join(s['widths'])}, blocks {join(s['blocks'])}{cost}; trained {trained}"


def untrained_variants(quick: bool) -> list[tuple[str, dict]]:
    """(label, network.build kwargs): the presets plus extra width and depth points."""
    if quick:
        return [("draft", {"preset": "draft"})]
    return [("draft", {"preset": "draft"}), ("standard", {"preset": "standard"}),
            ("final", {"preset": "final"}),
            ("standard narrow (widths/2)", {"preset": "standard", "widths": (16, 24, 48, 64)}),
            ("standard shallow (1 block/level)", {"preset": "standard", "blocks": (1, 1, 1, 1)}),
            ("standard wide (widths x1.5)", {"preset": "standard", "widths": (48, 72, 144, 192)})]


def file_stem(label: str) -> str:
    """A variant's label as a file name ("standard narrow (widths/2)" has a slash)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in label)


def quantised(session, frames, working: int, fullres, folder: pathlib.Path):
    """(int8 card or None, why not): static QDQ int8 of the model's convolutions, calibrated on
    what the network sees of the test frames (held out from training, not from this)."""
    import onnx

    from training.run import export

    card = session.card
    model = onnx.load(str(card.onnx_path))
    if not any(n.op_type == "Conv" for n in model.graph.node):
        return None, "no convolution to quantise in this model"
    feeds = []
    for f in frames[:8]:
        h, w = f.x_full.shape[1:]
        x_low = fullres.shrink_planar(f.x_full, *detail.working_shape(h, w, working))
        feeds.append(session.preprocess_planar(x_low, normalise.normalise_light(f.light)[0]).feeds)
    out = folder / f"{file_stem(card.name)}-int8.onnx"
    export.quantize_int8(card.onnx_path, out, feeds)
    return card_for(out, card.stride, card.working_size, f"{card.name}-int8", card.preset,
                    card.classes), ""


def half_precision(card: engine.ModelCard, folder: pathlib.Path) -> engine.ModelCard:
    """fp16 weights and activations (onnxruntime.transformers.float16), float32 inputs and
    outputs kept so the engine's contract holds."""
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    out = folder / f"{file_stem(card.name)}-fp16.onnx"
    onnx.save(convert_float_to_float16(onnx.load(str(card.onnx_path)), keep_io_types=True),
              str(out))
    return card_for(out, card.stride, card.working_size, f"{card.name}-fp16", card.preset,
                    card.classes)


def network_group(args, frames, folder: pathlib.Path, log, skipped) -> tuple[list[Row], dict]:
    """Every shipped model at every working size (detail on); for the first fp32 model: detail
    off, int8, fp16 and other providers; the trained width/depth points of --research; the
    untrained width/depth points that have no trained one. All timed together, interleaved."""
    res = frames[0].x_full.shape[1]
    fullres = detail.FullRes(threads=args.threads)
    cards = shipped_models(args.models, log=log)
    if not cards:
        log(f"no model in {args.models}: nothing trained to measure")
    if args.toy_fallback is not None:
        cards.append(args.toy_fallback)
    sizes = sorted({s for s in args.sizes if s < res} | {res})
    ctx = Context(args, res, sizes, folder, fullres, log)
    variants, own = [], {}
    for card in cards:
        s = open_session(card, args.threads, CPU)
        precision = "int8" if "int8" in card.name else "fp32"
        note = "toy model of the tests (physics stand-in)" if card is args.toy_fallback else ""
        for ws in sorted(set(sizes) | {min(card.working_size, res)}):
            variants.append(Variant("preset x resolution", ctx.name(card, ws, precision), s, ws,
                                    True, ctx.settings(card, ws, True, precision), note))
            if ws == min(card.working_size, res) and card is not args.toy_fallback:
                own[card.name] = (card, len(variants) - 1)
    primary = next((c for c in cards if "int8" not in c.name), None)
    fixed = []
    if primary is not None:
        more, fixed = primary_knobs(ctx, primary, cards, frames)
        variants += more
    research = research_variants(ctx, skipped)
    trained = [config_of(c) for c in cards] + [v.settings["config"] for v in research]
    variants += research + untrained(ctx, frames, [c for c in trained if c])
    results = measure_variants(variants, frames, fullres, args, log)
    rows = [network_row(v, r) for v, r in zip(variants, results)] + fixed
    per_card = {n: (card, results[i], variants[i].settings) for n, (card, i) in own.items()}
    return rows, per_card


def primary_knobs(ctx: Context, card, cards, frames) -> tuple[list[Variant], list[Row]]:
    """Detail transfer off, int8, fp16 and every non-CPU provider, for one model; (variants to
    measure, rows that say why a knob could not be measured)."""
    import onnxruntime as ort

    threads = ctx.args.threads
    s = open_session(card, threads, CPU)
    out = [Variant("detail transfer off", ctx.name(card, ws) + " no detail", s, ws, False,
                   ctx.settings(card, ws, False)) for ws in ctx.sizes if ws < ctx.res]
    ws, fixed = min(card.working_size, ctx.res), []
    q, why = quantised(s, frames, ws, ctx.fullres, ctx.folder)
    if q is None:
        ctx.log(f"int8 not measured: {why}")
        fixed.append(Row("network", "precision", ctx.name(card, ws, "int8"), None, None,
                         settings=ctx.settings(card, ws, True, "int8"), note=why))
    elif not any("int8" in c.name for c in cards):
        out.append(Variant("precision", ctx.name(card, ws, "int8"),
                           open_session(q, threads, CPU), ws, True,
                           ctx.settings(card, ws, True, "int8"),
                           "int8 QDQ (convolutions) made here, calibrated on the test frames"))
    out.append(Variant("precision", ctx.name(card, ws, "fp16"),
                       open_session(half_precision(card, ctx.folder), threads, CPU), ws, True,
                       ctx.settings(card, ws, True, "fp16"),
                       "fp16 made here (onnxruntime.transformers.float16, fp32 I/O)"))
    for prov in ort.get_available_providers():
        if prov not in (CPU, "AzureExecutionProvider"):
            out.append(Variant("provider", f"{ctx.name(card, ws)} {prov}",
                               open_session(card, threads, prov), ws, True,
                               ctx.settings(card, ws, True, "fp32", prov)))
    return out, fixed


def untrained(ctx: Context, frames, trained_configs: list[dict]) -> list[Variant]:
    """Speed of the presets and extra width/depth points exported untrained, for the configs
    that no trained model measured here has (and int8 / fp16 of the first): time is what these
    measure; their error is not an accuracy and is not reported."""
    from training.run import export
    from training.model import network

    if "untrained" in ctx.args.skip:
        return []
    ws, out = min(256, ctx.res), []
    nets = [(label, network.build(**kw).eval()) for label, kw in untrained_variants(ctx.args.quick)]
    todo = [(label, net) for label, net in nets if net.cfg.to_dict() not in trained_configs]
    for i, (label, net) in enumerate(todo):
        path = export.export_onnx(net, ctx.folder / f"untrained-{i}.onnx")
        card = card_for(path, net.cfg.stride, ws, label, label, contract.PARSING_CLASSES)
        variants = [("fp32", card)]
        if i == 0:
            q, _ = quantised(open_session(card, 1, CPU), frames, ws, ctx.fullres, ctx.folder)
            variants += [("int8", q)] if q is not None else []
            variants.append(("fp16", half_precision(card, ctx.folder)))
        extra = {"gflop_at_working": round(network.count_flops(net, ws, ws) / 1e9, 3),
                 "parameters": network.parameter_count(net)}
        for precision, c in variants:
            out.append(Variant(
                "untrained width/depth (time only)", f"{label} {precision} {ws}",
                open_session(c, ctx.args.threads, CPU), ws, True,
                {"model": label, "working": ws, "detail": True, "precision": precision,
                 "provider": CPU, "threads": ctx.args.threads, "config": net.cfg.to_dict()},
                "untrained export: time only, accuracy not measured", False, dict(extra)))
    return out


def reference_rows(samples) -> list[Row]:
    from training.eval import metrics

    rows = []
    for name, fn, note in (("identity (input unchanged)", metrics.baseline_identity, ""),
                           ("irradiance ratio (oracle source light)",
                            metrics.baseline_irradiance_ratio, "uses the true source light")):
        m = [metrics.image_metrics(fn(s), s["gt_t_k"], s["mask_t"][0] > 0.5) for s in samples]
        rows.append(Row("reference", "baseline", name, float(np.mean([x["rmse"] for x in m])),
                        None, note=note,
                        extra={"psnr": float(np.mean([x["psnr"] for x in m])),
                               "ssim": float(np.mean([x["ssim"] for x in m]))}))
    return rows


# ---- the light stage's effect shortcuts ---------------------------------------------------

def lightstage_group(args, log) -> list[Row]:
    import torch

    from bench import lightstage_throughput as lt
    from training.data.dataset import LightStageDataset

    torch.set_num_threads(1)
    ds = LightStageDataset("test", args.lightstage_res, seed=args.seed,
                           length=args.lightstage_samples)
    energies = (0.95, 0.8) if args.quick else (0.99, 0.95, 0.9, 0.8)
    runs = []
    for i in range(max(1, args.lightstage_repeats)):
        log(f"light stage shortcuts, pass {i + 1}")
        runs.append(lt.selective(ds, args.lightstage_samples, energies))
    rows = []
    full = spread([r[0][4] / 1e3 for r in runs])
    rows.append(Row("light stage", "effects", "all 114 lights", 0.0, full["ms"], full["p10"],
                    full["p90"], full["runs"], {"resolution": args.lightstage_res,
                                                "samples": args.lightstage_samples}))
    for j, e in enumerate(energies):
        t = spread([r[j][5] / 1e3 for r in runs])
        rows.append(Row("light stage", "effects", f"effects for {e:.0%} energy",
                        float(np.mean([r[j][2] for r in runs])), t["ms"], t["p10"], t["p90"],
                        t["runs"], {"energy": e, "resolution": args.lightstage_res,
                                    "samples": args.lightstage_samples},
                        {"lights_with_effects": float(np.mean([r[j][1] for r in runs])),
                         "max_error": float(np.max([r[j][3] for r in runs]))},
                        "timings are medians over the samples of each pass"))
    return rows


# ---- lighting conversion against the Cycles referee ---------------------------------------

def conversion_group(args, folder: pathlib.Path, log) -> list[Row]:
    """HDRI working width against the Cycles referee. The world is turned 33 degrees (a Mapping
    node): unturned, the pixel blocks line up with the light-vector cells and every width gives
    the same light vector, which would hide the trade-off."""
    import math

    from bench import light_conversion as lc  # imports bpy: only here

    hdri, hdri_io, lightvec = (lc.addon_module(m) for m in ("hdri", "hdri_io", "lightvec"))
    widths = (128, 256) if args.quick else (128, 256, 512, 1024)
    maps = [("synthetic 128x64", lc.write_exr(folder / "synthetic.exr", lc.synthetic_hdri()))]
    studio = ROOT.parent / "shared" / "data" / "hdri" / "blender" / "studio.exr"
    if studio.is_file() and not args.quick:
        maps.append(("Blender studio.exr 1024x512", str(studio)))
    res, samples, turn = (24, 64, 33.0) if args.quick else (48, 256, 33.0)
    a = math.radians(20.0)  # power is checked from a camera pitched 20 degrees, as lc does
    pitch = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    tilted = pitch @ hdri.FRONT_VIEW_WORLD_TO_FRAME
    rows = []
    for label, path in maps:
        log(f"Cycles referee: {label}")
        results = lc.world_case(path, str(folder), res=res, samples=samples, widths=widths,
                                mapping_z_deg=turn)
        image = np.clip(np.nan_to_num(hdri_io.read_hdri(path)), 0, None)
        h, w = image.shape[:2]
        truth = (image.astype(np.float64) * hdri.pixel_row_solid_angles(h, w)[:, None, None]
                 ).sum((0, 1))
        fns = [lambda _, w=width: hdri.downsample(image, yaw_degrees=-turn, max_width=w)
               for width in results]
        times = interleaved_times(fns, args.repeats, args.warmup)
        for (width, r), t in zip(results.items(), times):
            power = lightvec.total_power(hdri.downsample(image, tilted, yaw_degrees=-turn,
                                                         max_width=width))
            rows.append(Row("lighting conversion", label, f"width {width}", r["error"], t["ms"],
                            t["p10"], t["p90"], t["runs"],
                            {"hdri_width": width, "world_turn_deg": turn,
                             "render": f"{res}x{res}, {samples} samples"},
                            {"power_error": float(np.abs(power / truth - 1).max())},
                            "time: hdri.downsample of the whole map"))
    return rows


# ---- frontier, outputs --------------------------------------------------------------------

def front_of(row: Row) -> str:
    """Rows compete within their group; conversion rows only within their own HDRI (two maps
    have different errors at any width, so one frontier across them would mean nothing)."""
    return f"{row.group}: {row.kind}" if row.group == "lighting conversion" else row.group


def mark_frontier(rows: list[Row]) -> None:
    """Within each front (see front_of), a row is on the frontier when no other row is at least
    as fast and at least as accurate, and strictly better in one."""
    for row in rows:
        row.frontier = False
    for front in {front_of(r) for r in rows}:
        pts = [r for r in rows if front_of(r) == front and r.error is not None
               and r.ms is not None]
        for r in pts:
            r.frontier = not any(o.ms <= r.ms and o.error <= r.error
                                 and (o.ms < r.ms or o.error < r.error) for o in pts)


ERROR_NAMES = {"network": "RMSE (portrait region, display [0,1])",
               "light stage": "rel. RMSE vs full 114-light sum",
               "lighting conversion": "rel. RMSE vs Cycles",
               "reference": "RMSE (portrait region, display [0,1])"}
TIME_NAMES = {"network": "ms per frame", "light stage": "ms per frame (shading)",
              "lighting conversion": "ms per conversion", "reference": "-"}


def _num(v, fmt="{:.4f}"):
    return "-" if v is None else fmt.format(v)


def markdown(rows: list[Row], info: dict) -> str:
    lines = [f"Machine: {machine_line(info['machine'])}.",
             f"Test set: {info['test_set']}.",
             f"Command: `{info['command']}`. Timings: median of the runs (p10-p90 in brackets); "
             "the network rows time the per-frame stages of addon/pipeline.py (shrink, network, "
             "detail transfer, finish) at the test set's resolution, without decoding or writing.",
             f"Precision: {info['fp16']}", f"Providers: {info['providers_note']}", ""]
    for group in ("network", "reference", "light stage", "lighting conversion"):
        g = [r for r in rows if r.group == group]
        if not g:
            continue
        lines += [f"**{group}** (error: {ERROR_NAMES[group]}; time: {TIME_NAMES[group]})", "",
                  "| knob | setting | error | PSNR / other | time (p10-p90) | frontier | note |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in sorted(g, key=lambda r: (r.kind, r.ms or 0)):
            t = "-" if r.ms is None else f"{r.ms:.1f} ({r.p10:.1f}-{r.p90:.1f})" \
                if r.p10 is not None else f"{r.ms:.1f}"
            psnr = _num(r.extra.get("psnr"), "{:.2f}")
            if "power_error" in r.extra:
                psnr = f"power {r.extra['power_error']:.2%}"
            lines.append(f"| {r.kind} | {r.label} | {_num(r.error)} | {psnr} | {t} | "
                         f"{'**yes**' if r.frontier else ''} | {r.note} |")
        lines.append("")
    for note in info.get("skipped", []):
        lines.append(f"- not measured: {note}")
    return "\n".join(lines).rstrip() + "\n"


def make_plot(path, rows: list[Row], info: dict) -> None:
    """frontier.png: one panel per group (network, light stage, lighting conversion) of error
    against time (log), points coloured by knob, each front's Pareto frontier ringed and joined in
    red (report.HIGHLIGHT) with its labels, and the baselines, which take no time, as dashed lines
    in the network panel."""
    from matplotlib.ticker import LogLocator, NullFormatter, StrMethodFormatter

    groups = [g for g in ("network", "light stage", "lighting conversion")
              if any(r.group == g and r.error is not None and r.ms for r in rows)]
    m = info["machine"]
    load = f"load {m['load_avg_1_5_15'][0]}" + (f"-{m['load_avg_end']}" if m.get(
        "load_avg_end") is not None else "")
    fig, axes = report.figure(len(groups), f"{m['cpu']}, {m['cores']} cores, {load}, {m['date']}. "
                                           "Ringed + red line: Pareto frontier. Dashed: baselines.")
    if not groups:
        axes[0].text(0.5, 0.5, "no data", ha="center", va="center", transform=axes[0].transAxes)
    for ax, group in zip(axes, groups):
        pts = [r for r in rows if r.group == group and r.error is not None and r.ms]
        for i, kind in enumerate(sorted({r.kind for r in pts})):
            sel = [r for r in pts if r.kind == kind]
            ax.scatter([r.ms for r in sel], [r.error for r in sel], s=30, marker="s",
                       color=report.COLOURS[i % len(report.COLOURS)], label=kind, zorder=3)
        for front in sorted({front_of(r) for r in pts}):
            line = sorted((r for r in pts if r.frontier and front_of(r) == front),
                          key=lambda r: r.ms)
            ax.plot([r.ms for r in line], [r.error for r in line], color=report.HIGHLIGHT, lw=2,
                    zorder=2)
            ax.scatter([r.ms for r in line], [r.error for r in line], s=150, facecolors="none",
                       edgecolors=report.HIGHLIGHT, linewidths=1.5, zorder=4)
            for r in line:
                ax.annotate(r.label[:24], (r.ms, r.error), xytext=(5, 6),
                            textcoords="offset points", fontsize=6)
        if group == "network":
            for r in rows:
                if r.group == "reference" and r.error is not None:
                    ax.axhline(r.error, color="grey", ls="--", lw=1, zorder=1)
                    ax.annotate(r.label[:40], (1.0, r.error), xycoords=("axes fraction", "data"),
                                ha="right", va="bottom", fontsize=6, color="dimgrey")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(bottom=min(0.0, min(r.error for r in pts)))
        ax.set_title(group)
        ax.set_xlabel(TIME_NAMES[group] + " (log)")
        ax.set_ylabel(ERROR_NAMES[group])
        ax.grid(True, which="major", alpha=0.25)
        ax.legend(loc="lower left", fontsize=6)  # the fast and accurate corner stays empty
    fig.savefig(path)


def card_entry(card, result, settings, info) -> dict:
    return {"ms_per_frame": round(result["ms"], 2), "p10_ms": round(result["p10"], 2),
            "p90_ms": round(result["p90"], 2), "runs": result["runs"],
            "rmse": round(result["rmse"], 5), "psnr": round(result["psnr"], 3),
            "ssim": round(result["ssim"], 4), "working_size": settings["working"],
            "full_size": settings["full"], "detail_transfer": settings["detail"],
            "provider": settings["provider"], "threads": settings["threads"],
            "test_set": info["test_set"], "machine": machine_line(info["machine"]),
            "date": info["machine"]["date"], "command": info["command"],
            "what": "per-frame pipeline time (shrink, network, detail transfer, finish) and "
                    "held-out RMSE on the portrait region (training/eval/evaluate.py)"}


def write_cards(per_card: dict, info: dict) -> list[str]:
    written = []
    for card, result, settings in per_card.values():
        data = json.loads(card.card_path.read_text(encoding="utf-8"))
        data["frontier"] = card_entry(card, result, settings, info)
        card.card_path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
        written.append(str(card.card_path))
    return written


# ---- main ---------------------------------------------------------------------------------

def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny test set, few repeats")
    p.add_argument("--models", type=pathlib.Path, default=ROOT / "models")
    p.add_argument("--research", type=pathlib.Path,
                   help="trained width/depth points (ablation-full, width-narrow, width-deep "
                        ".onnx + cards; default: MODELS/research)")
    p.add_argument("--out", type=pathlib.Path, default=ROOT / "bench" / "results")
    p.add_argument("--write-cards", action="store_true",
                   help="add the per-preset figures to the measured model cards")
    p.add_argument("--resolution", type=int, help="test set size (default 640; quick 64)")
    p.add_argument("--samples", type=int, help="test samples (default 8; quick 2)")
    p.add_argument("--repeats", type=int, help="timed runs per setting (default 12; quick 3)")
    p.add_argument("--warmup", type=int, default=3,
                   help="untimed runs of every setting before timing starts")
    p.add_argument("--sizes", type=int, nargs="+",
                   help="working sizes below full (default 256 384 512; quick 16 32)")
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--cache", type=pathlib.Path, default=default_cache(),
                   help="where rendered test samples are kept between runs")
    p.add_argument("--no-cache", action="store_true")
    p.add_argument("--toy", action="store_true",
                   help="also measure the toy model of tests/onnx_fixtures.py (tests only)")
    p.add_argument("--skip", nargs="*", default=[],
                   choices=["untrained", "research", "lightstage", "conversion"])
    a = p.parse_args(argv)
    a.research = a.research or a.models / "research"
    a.resolution = a.resolution or (64 if a.quick else 640)
    a.samples = a.samples or (2 if a.quick else 8)
    a.repeats = a.repeats or (3 if a.quick else 12)
    a.sizes = a.sizes or ((16, 32) if a.quick else FULL_SIZES)
    a.lightstage_res = 48 if a.quick else 128
    a.lightstage_samples = 1 if a.quick else 4
    a.lightstage_repeats = 3
    return a


def _toy_card(folder: pathlib.Path):
    from tests.onnx_fixtures import write_toy_model  # the toy lives with the tests

    return engine.load_card(write_toy_model(folder))


def main(argv=None) -> dict:
    args = parse_args(argv)
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:6.1f}s] {msg}", flush=True)

    import torch

    torch.set_num_threads(1)
    info = {"machine": machine(), "command": "python -m bench.frontier " + " ".join(
        sys.argv[1:] if argv is None else argv)}
    log(f"machine: {machine_line(info['machine'])}")
    if info["machine"]["load_avg_1_5_15"][0] >= QUIET_LOAD:
        log(f"warning: load average >= {QUIET_LOAD}; timings will be noisy")
    skipped = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        args.toy_fallback = _toy_card(folder / "toy") if args.toy else None
        if args.skip:
            skipped += [f"{s} (skipped by --skip)" for s in args.skip]
        log(f"test set: {args.samples} held-out samples at {args.resolution} px")
        samples, info["test_set"] = heldout_samples(
            args.resolution, args.samples, args.seed, folder if args.no_cache else args.cache)
        frames = frames_of(samples)
        rows, per_card = network_group(args, frames, folder, log, skipped)
        rows += reference_rows(samples)
        if "lightstage" not in args.skip:
            rows += lightstage_group(args, log)
        if "conversion" not in args.skip:
            rows += conversion_group(args, folder, log)
    mark_frontier(rows)
    info["machine"]["load_avg_end"] = round(os.getloadavg()[0], 2) if hasattr(
        os, "getloadavg") else None
    loads = [info["machine"]["load_avg_1_5_15"][0], info["machine"]["load_avg_end"]]
    if any(x is not None and x >= QUIET_LOAD for x in loads):
        skipped.append(f"a quiet machine: the load average reached {max(x for x in loads if x)} "
                       f"(>= {QUIET_LOAD}): other work shared the cores, so timings are noisy "
                       "(the p10-p90 spread shows how much)")
    import onnxruntime as ort

    gpu = [p for p in ort.get_available_providers()
           if p not in ("CPUExecutionProvider", "AzureExecutionProvider")]
    info["providers_note"] = (f"measured on {', '.join(['CPU'] + gpu)}" + (
        "" if gpu else "; no GPU provider is present on this machine (CPU build of onnxruntime, "
                       "no GPU), so none is measured"))
    info["fp16"] = ("fp32, int8 (static QDQ, convolutions only) and fp16 (weights and "
                    "activations; float32 inputs and outputs) measured, all on the same "
                    "provider(s) listed below")
    info["skipped"] = skipped
    args.out.mkdir(parents=True, exist_ok=True)
    md = markdown(rows, info)
    (args.out / "frontier.md").write_text(md, encoding="utf-8")
    (args.out / "frontier.json").write_text(json.dumps(
        {"info": info, "rows": [asdict(r) for r in rows]}, indent=2, default=str) + "\n",
        encoding="utf-8")
    make_plot(args.out / "frontier.png", rows, info)
    cards = write_cards(per_card, info) if args.write_cards else []
    log(f"wrote {args.out / 'frontier.md'}, .json, .png" + (f"; cards: {cards}" if cards else ""))
    print(md)
    return {"rows": rows, "info": info, "cards": cards}


if __name__ == "__main__":
    main()
