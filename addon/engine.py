"""The onnxruntime engine: model cards, checked loading, and one relighting call split into
pre-process / process / post-process (after rembg's session classes).

The session object holds only what loading decided (the onnxruntime session, the card, the
providers); every call passes its data through arguments and return values, so one session can
serve several threads and a resumed run behaves exactly like a fresh one.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
from dataclasses import dataclass

import numpy as np

from . import contract, intrinsic, lightvec
from .errors import DependencyError, InputError, ModelError

# Fastest first. The CPU provider is always last so a machine without a GPU still runs.
PROVIDER_PREFERENCE = ("CUDAExecutionProvider", "CoreMLExecutionProvider",
                       "DmlExecutionProvider", "CPUExecutionProvider")


@dataclass(frozen=True)
class ModelCard:
    """A checked model card (models/<name>.json, see load_card): what the engine relies on, and
    the measured figures the panel and the batch script show; ``data`` holds it all."""
    card_path: pathlib.Path
    onnx_path: pathlib.Path
    name: str
    preset: str
    contract: str
    sha256: str
    stride: int
    working_size: int
    classes: tuple[str, ...]
    data: dict

    @property
    def foreground_channel(self) -> int:
        return self.classes.index(contract.FOREGROUND_CLASS)

    @property
    def recommended(self) -> bool:
        """Whether the card is marked as the preset to use when none is chosen."""
        return self.data.get("recommended") is True

    @property
    def title(self) -> str:
        """The preset as the panel names it: "portrait" is Portrait, "final-int8" Final (int8)."""
        name, _, variant = self.preset.partition("-")
        return name.replace("_", " ").title() + (f" ({variant})" if variant else "")

    @property
    def timing(self) -> tuple[float | None, str]:
        """(ms per frame, what the time refers to, e.g. "512 px, CPU"): bench/frontier.py's
        figure (the whole per-frame path; bench/intrinsic_frontier.py's for an intrinsic model)
        where the card has one, else export's CPU time of the network at the size nearest the
        working size; (None, "") when the card has neither."""
        front = self.data.get("frontier")
        if front:
            provider = str(front.get("provider", "CPU")).replace("ExecutionProvider", "").upper()
            return float(front["ms_per_frame"]), f"{front['working_size']} px, {provider}"
        sizes = self.data.get("cost", {}).get("cpu", {}).get("per_size")
        if not sizes:
            return None, ""
        size = min(sizes, key=lambda k: abs(int(k) - self.working_size))
        return float(sizes[size]["ms"]), f"{size} px, CPU"

    @property
    def ms_per_frame(self) -> float | None:
        return self.timing[0]

    @property
    def held_out_error(self) -> tuple[float | None, str]:
        """(held-out error, its name): for an intrinsic model the card's RMSE on held-out
        identities once its level is set (it keeps the footage's exposure, so that is its
        comparable figure); else bench/frontier.py's RMSE where the card has one, else the
        card's own RMSE; (None, "") if none."""
        model = self.data.get("metrics", {}).get("model", {})
        if self.contract == contract.INTRINSIC_CONTRACT and "rmse_level_fit" in model:
            return float(model["rmse_level_fit"]), "RMSE at the right level"
        front = self.data.get("frontier")
        if front and "rmse" in front:
            return float(front["rmse"]), "RMSE"
        if "rmse" in model:
            return float(model["rmse"]), "RMSE"
        return None, ""

    @property
    def summary(self) -> str:
        """Time per frame and held-out error, as the panel and the batch script's --help show."""
        ms, timed_at = self.timing
        error, error_name = self.held_out_error
        t = f"{ms:.0f} ms/frame ({timed_at})" if ms is not None else "time not measured"
        e = (f"held-out {error_name} {error:.3g}" if error is not None
             else "error not measured")
        return f"{t}, {e}"


MAX_CARD_NESTING = 32  # real cards nest 4-5 levels


def _nesting(tree) -> int:
    """How deeply lists and dicts nest in parsed JSON (iteratively: no recursion limit)."""
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, (dict, list)):
            deepest = max(deepest, depth)
            stack.extend((v, depth + 1) for v in (node.values() if isinstance(node, dict)
                                                  else node))
    return deepest


def card_path_for(model_path) -> pathlib.Path:
    return pathlib.Path(model_path).with_suffix(".json")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _tensor_names(entries):
    """The names of a card's "inputs" or "outputs" list ([{"name", "shape", ...}, ...]), or None
    when it is laid out otherwise."""
    if not isinstance(entries, list) or not all(
            isinstance(e, dict) and isinstance(e.get("name"), str)
            and isinstance(e.get("shape"), list) for e in entries):
        return None
    return tuple(e["name"] for e in entries)


def layout_problems(data: dict) -> list[str]:
    """How ``data`` departs from the one card layout the exporters write (training/run/export.py,
    training/intrinsic/export.py); empty when it does not. The contract is already known."""
    name = data["contract"]
    problems = [f"'{k}' is not a string" for k in ("name", "preset", "onnx", "sha256")
                if not isinstance(data[k], str)]
    for key, want, extra in (("inputs", contract.INPUTS[name], ()),
                             ("outputs", contract.OUTPUTS[name], contract.OPTIONAL_OUTPUTS[name])):
        if _tensor_names(data[key]) not in (want, want + extra):
            more = f" (then optionally {', '.join(extra)})" if extra else ""
            problems.append(f"'{key}' is not the list of {', '.join(want)}{more}")
    problems += [f"'{k}' is not a whole number" for k in ("stride", "working_size")
                 if not isinstance(data[k], int) or isinstance(data[k], bool)]
    if not (isinstance(data["classes"], list)
            and all(isinstance(c, str) for c in data["classes"])):
        problems.append("'classes' is not a list of names")
    problems += [f"'{k}' is not an object" for k in ("colour", "training", "metrics", "cost")
                 if not isinstance(data[k], dict)]
    if name == contract.CONTRACT_VERSION and data.get("relit_scale") != contract.RELIT_SCALE:
        problems.append(f"'relit_scale' is {data.get('relit_scale')!r}, not "
                        f"{contract.RELIT_SCALE!r}")
    # Where the card has measured figures (the panel shows them), they are where export wrote them.
    cost = data["cost"] if isinstance(data["cost"], dict) else {}
    cpu = cost.get("cpu", {})
    sizes = cpu.get("per_size", {}) if isinstance(cpu, dict) else None
    if not (isinstance(sizes, dict) and all(
            k.isdigit() and isinstance(v, dict) and _is_number(v.get("ms"))
            for k, v in sizes.items())):
        problems.append("'cost.cpu' is not {\"per_size\": {\"<size>\": {\"ms\": ...}}}")
    metrics = data["metrics"] if isinstance(data["metrics"], dict) else {}
    model = metrics.get("model", {})
    if not (isinstance(model, dict) and all(_is_number(v) for k, v in model.items()
                                            if k in ("rmse", "rmse_level_fit"))):
        problems.append("'metrics.model' is not an object of figures")
    front = data.get("frontier")
    # bench/frontier.py's entry, or for an intrinsic model bench/intrinsic_frontier.py's (time
    # only: its error is the card's own, at the right level)
    need = ("ms_per_frame", "working_size") + (() if name == contract.INTRINSIC_CONTRACT
                                               else ("rmse",))
    if front is not None and not (isinstance(front, dict) and all(
            _is_number(front.get(k)) for k in need)):
        problems.append("'frontier' is not bench/frontier.py's entry")
    if not isinstance(data.get("recommended", False), bool):
        problems.append("'recommended' is not true or false")
    return problems


def load_card(model_path) -> ModelCard:
    """Read and check the card beside ``model_path`` (same stem, .json). Raises ModelError."""
    onnx_path = pathlib.Path(model_path)
    card_path = card_path_for(onnx_path)
    if not onnx_path.is_file():
        raise ModelError(f"The model file {onnx_path} does not exist. Install a model (see "
                         "models/README.md) or pick another preset.")
    if not card_path.is_file():
        raise ModelError(f"The model {onnx_path.name} has no model card ({card_path.name} is "
                         "missing beside it); reinstall the model with its card.")
    try:
        data = json.loads(card_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ModelError(f"The model card {card_path} cannot be read ({err}); reinstall the "
                         "model.") from err
    except RecursionError as err:  # the JSON decoder recurses once per nesting level
        raise ModelError(f"The model card {card_path} is nested too deeply to be a model card; "
                         "reinstall the model.") from err
    if not isinstance(data, dict):
        raise ModelError(f"The model card {card_path} is not a JSON object; reinstall the model.")
    if _nesting(data) > MAX_CARD_NESTING:
        raise ModelError(f"The model card {card_path} is nested more than {MAX_CARD_NESTING} "
                         "levels deep, which no model card is; reinstall the model.")
    missing = [k for k in contract.REQUIRED_CARD_KEYS if k not in data]
    if missing:
        raise ModelError(f"The model card {card_path.name} lacks {', '.join(missing)}; it was not "
                         "made for this add-on. Reinstall the model.")
    if data["contract"] not in contract.KNOWN_CONTRACTS:
        raise ModelError(
            f"The model {card_path.stem} uses contract '{data['contract']}', which this version "
            f"of the add-on does not know (it knows {', '.join(contract.KNOWN_CONTRACTS)}). "
            "Update the add-on, or use a model made for this version.")
    problems = layout_problems(data)
    if problems:
        raise ModelError(f"The model card {card_path.name} is not laid out as this add-on's "
                         f"exporters write cards ({'; '.join(problems)}). Reinstall the model "
                         "with its own card.")
    classes = tuple(data["classes"])
    if contract.FOREGROUND_CLASS not in classes:
        raise ModelError(f"The model card {card_path.name} has no '{contract.FOREGROUND_CLASS}' "
                         "parsing class; the matte cannot be made. Reinstall the model.")
    stride, working = data["stride"], data["working_size"]
    if stride < 1 or working < stride:
        raise ModelError(f"The model card {card_path.name} has stride {stride} and working size "
                         f"{working}, which cannot work; reinstall the model.")
    return ModelCard(card_path, onnx_path, data["name"], data["preset"], data["contract"],
                     data["sha256"].lower(), stride, working, classes, data)


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_model(card: ModelCard) -> bytes:
    """The .onnx file's bytes: the session is built from exactly the bytes that were checked."""
    try:
        return card.onnx_path.read_bytes()
    except OSError as err:
        raise ModelError(f"The model file {card.onnx_path} cannot be read ({err}); check its "
                         "permissions or reinstall the model.") from err


def verify_checksum(card: ModelCard, data: bytes | None = None) -> None:
    """Refuse a model file whose sha256 differs from its card (truncated download, edited file).
    ``data``: the file's bytes when already read (read_model)."""
    actual = file_sha256(card.onnx_path) if data is None else hashlib.sha256(data).hexdigest()
    if actual != card.sha256:
        raise ModelError(
            f"The model file {card.onnx_path.name} is corrupt or not the one its card describes "
            f"(sha256 {actual[:12]}... instead of {card.sha256[:12]}...). Download or reinstall "
            "the model.")


def refuse_external_data(card: ModelCard, data: bytes) -> None:
    """Refuse a model that keeps weights in files beside the .onnx: the card's checksum covers
    only the .onnx, so altered weights would load unnoticed (and onnxruntime would look for
    them relative to the working folder when the model is given as bytes)."""
    from . import onnx_graph

    try:
        external = onnx_graph.external_tensors(data)
    except ValueError as err:
        raise ModelError(f"The add-on cannot load {card.onnx_path.name}: it is not a valid ONNX "
                         f"model ({err}). Download or reinstall the model.") from err
    if external:
        shown = ", ".join(external[:3]) + (" ..." if len(external) > 3 else "")
        raise ModelError(
            f"The model {card.onnx_path.name} keeps {len(external)} weight tensor(s) ({shown}) "
            "in separate files, which its card's checksum does not cover, so the add-on does "
            "not load it. Use a model saved as one .onnx file (onnx.save_model(model, path, "
            "save_as_external_data=False)) with its card.")


def choose_providers(available, requested=None) -> list[str]:
    """Execution providers to use, best first, always ending with the CPU provider.

    ``requested`` (names, in order) overrides the preference; names not available here are
    dropped, and if none remain the preference order applies."""
    available = list(available)
    order = list(requested) if requested else list(PROVIDER_PREFERENCE)
    chosen = [p for p in order if p in available]
    if not chosen:
        chosen = [p for p in PROVIDER_PREFERENCE if p in available]
    if "CPUExecutionProvider" in available and "CPUExecutionProvider" not in chosen:
        chosen.append("CPUExecutionProvider")
    return chosen


def import_onnxruntime():
    """The onnxruntime module, or a DependencyError saying to reinstall the extension."""
    try:
        import onnxruntime
    except ImportError as err:  # the extension still loads and can say what is missing
        raise DependencyError(
            "onnxruntime is not installed or cannot load on this system; reinstall the "
            f"extension for your platform ({err}).") from err
    return onnxruntime


def session_options(ort, threads: int | None = None, spin: bool = True):
    """Explicit options: all graph optimisations, sequential execution, ``threads`` intra-op
    threads (None = one per core). ``spin=False`` stops idle worker threads spinning, which
    matters when decode/write threads share the cores."""
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.intra_op_num_threads = int(threads) if threads else 0
    so.inter_op_num_threads = 1
    so.log_severity_level = 3  # errors only: warnings about unused providers are noise here
    if not spin:
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return so


def pad_to_stride(image: np.ndarray, stride: int) -> tuple[np.ndarray, int, int]:
    """(a (3, H, W) float32 image reflect-padded at the bottom and right to a multiple of
    ``stride``, its original H and W); ValueError for any other shape."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[0] != 3 or img.shape[1] < 1 or img.shape[2] < 1:
        raise ValueError(f"image must be (3, H, W), got {img.shape}")
    h, w = img.shape[1:]
    ph, pw = -h % stride, -w % stride
    if ph or pw:
        img = np.pad(img, ((0, 0), (0, ph), (0, pw)), mode="reflect" if min(h, w) > 1 else "edge")
    return img, h, w


@dataclass(frozen=True)
class EngineResult:
    relit: np.ndarray         # (3, H, W) float32, the image's units
    source_light: np.ndarray  # (16, 16, 3) float32
    parsing: np.ndarray       # (K, H, W) float32 in [0, 1], channel order = card.classes


@dataclass(frozen=True)
class Prepared:
    feeds: dict
    height: int
    width: int


class RelightSession:
    """A loaded model: ``run_planar(image, light)``, or its three stages separately
    (preprocess_planar, process, postprocess_planar); images are channels first (3, H, W)."""

    def __init__(self, session, card: ModelCard, providers: list[str]):
        self.session = session
        self.card = card
        self.providers = providers
        self._check_io()

    def _check_io(self) -> None:
        ins = {i.name for i in self.session.get_inputs()}
        outs = {o.name for o in self.session.get_outputs()}
        need_in = {contract.INPUT_IMAGE, contract.INPUT_LIGHT}
        need_out = {contract.OUTPUT_RELIT, contract.OUTPUT_SOURCE_LIGHT, contract.OUTPUT_PARSING}
        if not need_in <= ins or not need_out <= outs:
            raise ModelError(
                f"The model {self.card.onnx_path.name} does not follow contract "
                f"{self.card.contract}: it needs inputs {sorted(need_in)} and outputs "
                f"{sorted(need_out)}, it has {sorted(ins)} and {sorted(outs)}. Reinstall it.")

    def preprocess_planar(self, image: np.ndarray, light: np.ndarray) -> Prepared:
        """(3, H, W) normalised linear image and a (16, 16, 3) normalised light -> feeds, with
        the image reflect-padded at the bottom and right to a multiple of the model's stride (no
        copy when no padding is needed and the image is contiguous float32)."""
        img, h, w = pad_to_stride(image, self.card.stride)
        chw = np.ascontiguousarray(img[None])
        lt = np.ascontiguousarray(lightvec.validate(light).transpose(2, 0, 1)[None])
        return Prepared({contract.INPUT_IMAGE: chw, contract.INPUT_LIGHT: lt}, h, w)

    def process(self, prepared: Prepared) -> dict:
        names = [contract.OUTPUT_RELIT, contract.OUTPUT_SOURCE_LIGHT, contract.OUTPUT_PARSING]
        return dict(zip(names, self.session.run(names, prepared.feeds)))

    def postprocess_planar(self, outputs: dict, prepared: Prepared) -> EngineResult:
        """Check every shape and crop the padding away; relit stays channels-first (3, H, W)."""
        h, w = prepared.height, prepared.width
        hp, wp = prepared.feeds[contract.INPUT_IMAGE].shape[2:]
        relit = outputs[contract.OUTPUT_RELIT]
        src = outputs[contract.OUTPUT_SOURCE_LIGHT]
        par = outputs[contract.OUTPUT_PARSING]
        k = len(self.card.classes)
        if (relit.shape != (1, 3, hp, wp) or src.shape != (1, 3, 16, 16)
                or par.shape != (1, k, hp, wp)):
            raise ModelError(
                f"The model {self.card.onnx_path.name} returned shapes relit {relit.shape}, "
                f"source_light {src.shape}, parsing {par.shape} for a {hp}x{wp} input; the "
                f"contract needs (1,3,{hp},{wp}), (1,3,16,16), (1,{k},{hp},{wp}). The model "
                "or its card is wrong; reinstall it.")
        return EngineResult(
            relit=np.ascontiguousarray(relit[0, :, :h, :w], dtype=np.float32),
            source_light=np.ascontiguousarray(src[0].transpose(1, 2, 0), dtype=np.float32),
            parsing=np.ascontiguousarray(par[0, :, :h, :w], dtype=np.float32))

    def run_planar(self, image: np.ndarray, light: np.ndarray) -> EngineResult:
        prepared = self.preprocess_planar(image, light)
        return self.postprocess_planar(self.process(prepared), prepared)


@dataclass(frozen=True)
class IntrinsicResult:
    """An intrinsic model's buffers for one image, channels first, cropped to the input's size."""
    normal: np.ndarray   # (3, H, W)
    height: np.ndarray   # (H, W)
    albedo: np.ndarray   # (3, H, W)
    parsing: np.ndarray  # (K, H, W), channel order = card.classes
    transfer: np.ndarray | None = None  # (16, H, W) when the model has contract.OUTPUT_TRANSFER


def _mirror_mean(name: str, out: np.ndarray) -> np.ndarray:
    """(1, C, H, W): the mean of a batch's two buffers, the second (the mirror image's) mirrored
    back, its x-odd channels negated."""
    back = out[1, :, :, ::-1].copy()
    if name == contract.OUTPUT_NORMAL:
        back[0] *= -1.0
    elif name == contract.OUTPUT_TRANSFER and back.shape[0] == contract.TRANSFER_CHANNELS:
        back[list(contract.TRANSFER_X_ODD)] *= -1.0
    return (0.5 * (out[0] + back))[None]


class IntrinsicSession:
    """A loaded intrinsic model (contract.INTRINSIC_CONTRACT): ``run_planar(image)`` gives the
    buffers that addon/intrinsic.py renders; the light never enters the network."""

    OUTPUTS = (contract.OUTPUT_NORMAL, contract.OUTPUT_HEIGHT, contract.OUTPUT_ALBEDO,
               contract.OUTPUT_PARSING)

    def __init__(self, session, card: ModelCard, providers: list[str]):
        self.session = session
        self.card = card
        self.providers = providers
        ins = {i.name for i in session.get_inputs()}
        outs = {o.name for o in session.get_outputs()}
        if contract.INPUT_IMAGE not in ins or not set(self.OUTPUTS) <= outs:
            raise ModelError(
                f"The model {card.onnx_path.name} does not follow contract {card.contract}: it "
                f"needs input {contract.INPUT_IMAGE!r} and outputs {sorted(self.OUTPUTS)}, it has "
                f"{sorted(ins)} and {sorted(outs)}. Reinstall it.")
        self.outputs = self.OUTPUTS + ((contract.OUTPUT_TRANSFER,)
                                       if contract.OUTPUT_TRANSFER in outs else ())

    def run_planar(self, image: np.ndarray, mirror: bool = False) -> IntrinsicResult:
        """(3, H, W) normalised linear image (addon.intrinsic.exposure_scale) -> buffers; the
        image is reflect-padded to the model's stride and the buffers cropped back.
        ``mirror``: the image and its mirror image run as one batch, and each buffer is the mean
        of the image's and the mirror's, mirrored back (the normal's x and the transfer's x-odd
        coefficients change sign): the network, trained on randomly mirrored frames, errs
        differently on the two, and their mean errs less."""
        img, h, w = pad_to_stride(image, self.card.stride)
        batch = np.stack([img, img[:, :, ::-1]]) if mirror else img[None]
        outs = self.session.run(list(self.outputs),
                                {contract.INPUT_IMAGE: np.ascontiguousarray(batch)})
        if mirror:
            outs = [_mirror_mean(name, o) for name, o in zip(self.outputs, outs)]
        n, hgt, alb, par, *rest = (np.ascontiguousarray(o[0, :, :h, :w], dtype=np.float32)
                                   for o in outs)
        if mirror:
            n = intrinsic.unit_normals(n)
        tr = rest[0] if rest else None
        k = len(self.card.classes)
        if (n.shape[0] != 3 or hgt.shape[0] != 1 or alb.shape[0] != 3 or par.shape[0] != k
                or (tr is not None and tr.shape[0] != contract.TRANSFER_CHANNELS)):
            raise ModelError(f"The model {self.card.onnx_path.name} returned buffers of the wrong "
                             "shape for its card; reinstall it.")
        return IntrinsicResult(n, hgt[0], alb, par, tr)


def check_working_size(card: ModelCard, working_size) -> int:
    """The working size a run asks of ``card``'s network (None: the card's own): a positive
    whole number (the network pads its input to its stride); InputError otherwise."""
    if working_size is None:
        return card.working_size
    if isinstance(working_size, bool) or not isinstance(working_size, (int, np.integer)) \
            or working_size < 1:
        raise InputError(f"The working size must be a positive whole number of pixels, got "
                         f"{working_size!r}; {card.name}'s card says {card.working_size}.")
    return int(working_size)


def new_session(model_path, providers=None, threads: int | None = None, spin: bool = True,
                verify: bool = True, working_size: int | None = None):
    """Load a model after checking its card, its checksum and that it keeps no weights in other
    files (the session is built from the checked bytes): a RelightSession, or an
    IntrinsicSession for an intrinsic model. ``working_size``: the network's working size in
    place of the card's (check_working_size). Raises ModelError / DependencyError /
    InputError."""
    card = load_card(model_path)
    if working_size is not None:
        card = dataclasses.replace(card, working_size=check_working_size(card, working_size))
    data = read_model(card)
    if verify:
        verify_checksum(card, data)
    refuse_external_data(card, data)
    ort = import_onnxruntime()
    chosen = choose_providers(ort.get_available_providers(), providers)
    try:
        sess = ort.InferenceSession(data, sess_options=session_options(
            ort, threads, spin), providers=chosen)
    except Exception as err:  # onnxruntime raises its own untyped errors for bad files
        raise ModelError(f"onnxruntime cannot load {card.onnx_path.name} ({err}). The file is "
                         "damaged or made for a newer onnxruntime; reinstall the model.") from err
    kind = IntrinsicSession if card.contract == contract.INTRINSIC_CONTRACT else RelightSession
    return kind(sess, card, sess.get_providers())
