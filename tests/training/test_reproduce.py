"""training.run.reproduce: the shipped cards' recipes are valid commands of today's training CLI."""

import importlib.util
import json
import pathlib
import shlex

import pytest

from addon import contract
from training.intrinsic import export as intrinsic_export
from training.intrinsic import recover as intrinsic_recover
from training.intrinsic import train as intrinsic_train
from training.model import checkpoint
from training.run import export, lineage, options, reproduce

ROOT = pathlib.Path(__file__).resolve().parents[2]
CARDS = sorted((ROOT / "models").glob("*.json"))
ALL_CARDS = CARDS + sorted((ROOT / "models" / "research").glob("*.json"))


def _card(init=None, preset="draft", name="relight-draft"):
    recipe = {"command": "python -m training.train --preset draft --steps 10 --out runs/b",
              "args": {"out": "runs/b"}, "exported_checkpoint": {"file": "best.pt", "step": 10}}
    if init:
        recipe["init"] = {"checkpoint": "runs/a/best.pt", "step": 5, "recipe": init}
    return {"name": name, "preset": preset, "training": {"recipe": recipe}}


def test_a_continued_model_reproduces_its_first_run_then_the_second_then_the_export():
    """The card records the commands as run (here under the modules' former names); reproduce
    runs them under today's names."""
    first = "python -m training.train --preset draft --steps 5 --out runs/a"
    cmds = reproduce.commands(_card(init=first))
    assert cmds[0] == "python -m training.run.train --preset draft --steps 5 --out runs/a"
    assert cmds[1].startswith("python -m training.run.train ") and "--out runs/b" in cmds[1]
    assert cmds[2] == ("python -m training.run.export --run runs/b --checkpoint best.pt --name "
                       "relight-draft --threads 1 --eval 64")
    assert len(reproduce.commands(_card())) == 2
    int8 = reproduce.commands(_card(preset="final-int8", name="relight-final-int8"))
    assert int8[-1].endswith("--name relight-final --threads 1 --eval 64 --int8")


def test_an_intrinsic_card_reproduces_its_export_with_the_int8_flag_it_was_made_with():
    card = {**_card(preset="portrait", name="relight-portrait"),
            "contract": contract.INTRINSIC_CONTRACT, "recommended": True}
    plain = reproduce.commands(card)[-1]
    assert plain.startswith("python -m training.intrinsic.export ") and "--int8" not in plain
    int8 = reproduce.commands({**card, "quantisation": {"kind": "int8"}})[-1]
    assert int8 == plain + " --int8"
    assert intrinsic_export.parser().parse_args(shlex.split(int8)[3:]).int8
    # A card that measured long-haired identities measures them again, from the same frames.
    cmd = ("python -m training.intrinsic.data --split val --res 128 --frames 64 --long-hair 1 "
           "--out cache/intrinsic-longval")
    hair = reproduce.commands({**card, "metrics": {"val_buffers_long_hair": {"command": cmd}}})
    args = intrinsic_export.parser().parse_args(shlex.split(hair[-1])[3:])
    assert args.long_hair_val == "cache/intrinsic-longval" and not args.int8


def test_an_intrinsic_card_averaged_with_its_start_reproduces_the_same_average():
    """A card exported with --init-share records the share; reproduce exports with it."""
    card = {**_card(preset="portrait", name="relight-portrait"),
            "contract": contract.INTRINSIC_CONTRACT}
    assert "--init-share" not in reproduce.commands(card)[-1]
    card["training"]["init_share"] = {"share": 0.25, "init": "runs/a/best.pt"}
    last = reproduce.commands(card)[-1]
    assert intrinsic_export.parser().parse_args(shlex.split(last)[3:]).init_share == 0.25


def test_a_grafted_card_reproduces_its_graft_and_names_the_file_it_needs():
    """A card whose hair head was grafted onto a file exports with --graft-onto that file (not
    --int8: the file is already quantised), and reproduce says which version of the file the
    graft and the rebuild from it read (once, by sha256)."""
    base = {"onnx": "models/relight-portrait.onnx", "sha256": "ab" * 32}
    card = {**_card(preset="portrait", name="relight-portrait"),
            "contract": contract.INTRINSIC_CONTRACT, "quantisation": {"kind": "int8"},
            "graft": base}
    card["training"]["recipe"]["init"] = {"checkpoint": "runs/r/best.pt",
                                          "recipe": "python -m training.intrinsic.recover ...",
                                          "recovered_from": base}
    last = reproduce.commands(card)[-1]
    args = intrinsic_export.parser().parse_args(shlex.split(last)[3:])
    assert args.graft_onto == "models/relight-portrait.onnx" and not args.int8
    notes = reproduce.file_notes(card)
    assert len(notes) == 1 and "ab" * 32 in notes[0]
    assert reproduce.file_notes(_card()) == []


def test_a_model_trained_further_twice_reproduces_the_whole_chain(tmp_path):
    """lineage.load_init keeps the parent's own start (nested), completing an older one-level
    record from the parent checkpoint on disk; reproduce runs the chain from the first run."""
    from training.model import network

    net = network.build("draft")
    cmd = {k: f"python -m training.run.train --preset draft --steps 5 --out {tmp_path}/{k}"
           for k in "abc"}
    checkpoint.save_checkpoint(tmp_path / "a.pt", net, {"command": cmd["a"]}, 5)
    old_style = {"checkpoint": str(tmp_path / "a.pt"), "step": 5, "recipe": cmd["a"]}
    checkpoint.save_checkpoint(tmp_path / "b.pt", net, {"command": cmd["b"], "init": old_style}, 5)
    init = lineage.load_init(network.build("draft"), tmp_path / "b.pt")
    assert init["recipe"] == cmd["b"] and init["init"]["recipe"] == cmd["a"]
    assert init["init"]["init"] is None  # a run from scratch ends the chain
    card = {"name": "relight-draft", "preset": "draft", "training": {"recipe": {
        "command": cmd["c"], "args": {"out": f"{tmp_path}/c"}, "init": init}}}
    assert reproduce.commands(card)[:3] == [cmd["a"], cmd["b"], cmd["c"]]
    # a parent not on disk: the record stays as it was
    assert lineage.resolve_lineage({"checkpoint": str(tmp_path / "gone.pt"), "recipe": "x"}) == {
        "checkpoint": str(tmp_path / "gone.pt"), "recipe": "x"}


@pytest.mark.parametrize("card", CARDS, ids=[c.stem for c in CARDS])
def test_every_shipped_card_gives_commands_the_current_cli_accepts(card):
    cmds = reproduce.commands(json.loads(card.read_text()))
    for c in cmds:
        args = shlex.split(c)
        assert args[:2] == ["python", "-m"]
        if args[2] == "training.run.train":
            parsed = options.parser().parse_args(args[3:])
            assert parsed.steps > 0  # step budgets: the same work on any machine
        elif args[2] == "training.intrinsic.train":
            intrinsic_train.parser().parse_args(args[3:])
        elif args[2] == "training.intrinsic.export":
            intrinsic_export.parser().parse_args(args[3:])
        elif args[2] == "training.intrinsic.recover":  # a run rebuilt from a shipped file
            intrinsic_recover.parser().parse_args(args[3:])
        else:
            assert args[2] == "training.run.export"
            export.parser().parse_args(args[3:])
    runs = [c for c in cmds if shlex.split(c)[2] in
            ("training.run.train", "training.intrinsic.train", "training.intrinsic.recover")]
    for before, after in zip(runs, runs[1:]):  # each run starts from the one before it
        out = shlex.split(before)[shlex.split(before).index("--out") + 1]
        if shlex.split(after)[2] != "training.intrinsic.recover":  # that one reads a file
            assert f"--init {out}/" in after


def test_moved_modules_run_under_their_present_names():
    """MOVED maps each module name a card may have recorded to a module that exists today, and
    only the module of ``python -m`` is renamed."""
    for old, new in reproduce.MOVED.items():
        assert old != new and importlib.util.find_spec(new) is not None, new
    assert reproduce.current_command("python -m training.train --out runs/training.train") == (
        "python -m training.run.train --out runs/training.train")
    assert reproduce.current_command("python -m training.intrinsic.train --out x") == (
        "python -m training.intrinsic.train --out x")
    assert reproduce.current_module("training.make_testset") == "training.data.make_testset"


def test_a_missing_card_says_what_to_pass(tmp_path, capsys):
    assert reproduce.main([str(tmp_path / "nope.json")]) == 2
    assert "models/<name>.json" in capsys.readouterr().err


def test_each_run_in_the_chain_says_which_light_stage_samples_it_trained_on(tmp_path):
    """A chain that began on v1 samples and went on under v2: load_init records each parent's
    render version (v1 where the record predates the field), and reproduce names the runs that
    today's renderer cannot repeat weight for weight."""
    from training.model import network

    net = network.build("draft")
    checkpoint.save_checkpoint(tmp_path / "a.pt", net, {"command": "python -m training.train a",
                                                   "git_commit": "abc123"}, 5)
    init = lineage.load_init(network.build("draft"), tmp_path / "a.pt")
    assert init["render_version"] == "v1" and init["git_commit"] == "abc123"
    checkpoint.save_checkpoint(tmp_path / "b.pt", net, {"command": "python -m training.train b",
                                                   "init": init, "render_version": "v2"}, 5)
    init_b = lineage.load_init(network.build("draft"), tmp_path / "b.pt")
    assert init_b["render_version"] == "v2" and init_b["init"]["render_version"] == "v1"
    card = {"name": "relight-draft", "preset": "draft", "training": {"recipe": {
        "command": "python -m training.train c", "args": {"out": "runs/c"}, "init": init_b,
        "render_version": "v2"}}}
    assert [r["render_version"] for r in reproduce.chain(card)] == ["v1", "v2", "v2"]
    notes = reproduce.version_notes(card, "v2")
    assert len(notes) == 1 and notes[0].startswith("reproduce: run 1 trained on light stage v1")
    assert notes[0].endswith("(the code it ran: git checkout abc123)")
    assert reproduce.version_notes(card, "v1") and len(reproduce.version_notes(card, "v1")) == 2


@pytest.mark.parametrize("card", ALL_CARDS, ids=[c.stem for c in ALL_CARDS])
def test_every_committed_card_was_measured_on_the_current_light_stage(card):
    """A card's held-out figures come from the test set of today's render version (bumping
    training.data.dataset.RENDER_VERSION means re-measuring the cards: evaluate --update-card)."""
    from training.data.dataset import renderer_version

    metrics = json.loads(card.read_text())["metrics"]
    onnx = card.with_suffix(".onnx").relative_to(ROOT)
    assert metrics.get("render_version") == renderer_version(), (
        f"{card.name} was measured on light stage {metrics.get('render_version', 'v1')} samples; "
        f"re-measure: python -m training.eval.evaluate --onnx {onnx} --update-card")
    assert reproduce.current_module(metrics["testset"]) == "training.data.make_testset"
    assert len(metrics["testset_sha256"]) == 64


def test_all_committed_cards_were_measured_on_one_and_the_same_test_set():
    sets = {json.loads(c.read_text())["metrics"].get("testset_sha256") for c in ALL_CARDS}
    assert len(sets) == 1, f"cards measured on different test sets: {sorted(map(str, sets))}"
