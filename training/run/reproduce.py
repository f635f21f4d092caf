"""Reproduce a shipped model from its card: one command.

    .venv/bin/python -m training.run.reproduce models/relight-draft.json          # print them
    .venv/bin/python -m training.run.reproduce models/relight-draft.json --run    # and run them

A card's ``training.recipe`` holds the exact training command (every argument) and, for a model
trained further from another run (``--init``), that run's command too, and the command of the run
that one started from, back to a run from scratch; the commands run in order (each writes the
checkpoint the next starts from), then ``training.run.export`` writes the
ONNX and the card again (``--int8`` for an int8 card, from the same run). On this project's
2-core CPU the shipped presets take 40-120 minutes each; a GPU runs the same step budgets.

A card keeps the commands as they were run. Modules that have moved since are run under their
present names (``MOVED``: the old name, then the new one), so every card still reproduces.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shlex
import subprocess
import sys

from addon import contract

ROOT = pathlib.Path(__file__).resolve().parents[2]
MOVED = {
    "bench.temporal_stability": "training.eval.temporal_stability",
    "training.ablation": "training.eval.ablation",
    "training.before_after": "training.eval.before_after",
    "training.build_cache": "training.data.build_cache",
    "training.contact_sheet": "training.data.contact_sheet",
    "training.dataset": "training.data.dataset",
    "training.evaluate": "training.eval.evaluate",
    "training.export": "training.run.export",
    "training.footage_sheet": "training.eval.footage_sheet",
    "training.lighting_sampling": "training.data.lighting_sampling",
    "training.make_demo_clip": "training.data.make_demo_clip",
    "training.make_testset": "training.data.make_testset",
    "training.report": "training.eval.report",
    "training.reproduce": "training.run.reproduce",
    "training.train": "training.run.train",
    "training.yale_eval": "training.eval.yale",
}


def current_module(name: str) -> str:
    """A module's present name, given the name a card recorded."""
    return MOVED.get(name, name)


def current_command(command: str) -> str:
    """``python -m MODULE ...`` with MODULE under its present name; the rest kept as written."""
    return re.sub(r"(?<=-m )\S+", lambda m: current_module(m[0]), command, count=1)


def chain(card: dict) -> list[dict]:
    """The training runs behind ``card``, first to last: each a record with ``recipe`` (the
    command), ``git_commit`` (the code it ran, where recorded) and ``render_version`` (of the
    light stage samples it trained on; runs recorded before versions were kept trained on v1)."""
    def run(command: str, record: dict) -> dict:
        return {"recipe": command, "git_commit": record.get("git_commit"),
                "render_version": record.get("render_version") or "v1"}

    recipe = card["training"]["recipe"]
    runs, init = [], recipe.get("init")
    while init:  # the run it started from, that run's own start, ... (training.run.lineage)
        if init.get("recipe"):
            runs.append(run(init["recipe"], init))
        init = init.get("init")
    return runs[::-1] + [run(recipe["command"], recipe)]


def version_notes(card: dict, current: str) -> list[str]:
    """One line per run whose samples were of another render version than this code renders:
    those runs re-run with today's samples, so they reproduce the recipe, not the same weights."""
    return [f"reproduce: run {i + 1} trained on light stage {r['render_version']} samples; this "
            f"code renders {current}, so it reproduces that run's recipe, not its weights"
            + (f" (the code it ran: git checkout {r['git_commit']})" if r.get("git_commit") else "")
            for i, r in enumerate(chain(card)) if r["render_version"] != current]


def file_notes(card: dict) -> list[str]:
    """One line per shipped file a command reads as it was when the card was made: a run
    rebuilt from a file (training.intrinsic.recover) and a hair head grafted onto one (export
    --graft-onto) need that version of the file in place, which its sha256 finds in git."""
    files = []
    node = card["training"]["recipe"]
    while node:
        if node.get("recovered_from"):
            files.append(node["recovered_from"])
        node = node.get("init")
    if card.get("graft"):
        files.append(card["graft"])
    return [f"reproduce: put the {f['onnx']} whose sha256 is {f['sha256']} in place first "
            f"(git log -- {f['onnx']} finds it): a command reads that version"
            for f in {f["sha256"]: f for f in files}.values()]


def commands(card: dict) -> list[str]:
    """The shell commands that made the model of ``card``, in order."""
    recipe = card["training"]["recipe"]
    out = [current_command(r["recipe"]) for r in chain(card)]
    name, int8 = card["name"], str(card.get("preset", "")).endswith("-int8")
    if int8 and name.endswith("-int8"):
        name = name[: -len("-int8")]
    checkpoint = (recipe.get("exported_checkpoint") or {}).get("file", "best.pt")
    if card.get("contract") == contract.INTRINSIC_CONTRACT:
        share = card["training"].get("init_share")  # export --init-share
        long_hair = (card.get("metrics") or {}).get("val_buffers_long_hair") or {}
        long_val = shlex.split(long_hair.get("command", ""))
        out.append(f"python -m training.intrinsic.export --run {recipe['args']['out']} "
                   f"--checkpoint {checkpoint} --name {name}"
                   + (" --recommended" if card.get("recommended") is True else "")
                   + (f" --long-hair-val {long_val[long_val.index('--out') + 1]}"
                      if "--out" in long_val else "")
                   + (f" --init-share {share['share']:g}" if share else "")
                   + (f" --graft-onto {card['graft']['onnx']}" if card.get("graft")
                      else " --int8" if card.get("quantisation") else ""))
        return out
    out.append(f"python -m training.run.export --run {recipe['args']['out']} --checkpoint "
               f"{checkpoint} --name {name} --threads 1 --eval 64" + (" --int8" if int8 else ""))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("card", help="a model card (models/<name>.json)")
    p.add_argument("--run", action="store_true", help="run the commands (from the repository root)")
    a = p.parse_args(argv)
    path = pathlib.Path(a.card)
    if not path.is_file():
        print(f"reproduce: no model card at {path}; pass models/<name>.json", file=sys.stderr)
        return 2
    from ..data.dataset import renderer_version

    card = json.loads(path.read_text())
    cmds = commands(card)
    for c in cmds:
        print(c)
    for line in version_notes(card, renderer_version()) + file_notes(card):
        print(line, file=sys.stderr)
    if a.run:
        for c in cmds:
            args = shlex.split(c)
            if args[0] == "python":
                args[0] = sys.executable
            print(f"\n$ {c}", flush=True)
            done = subprocess.run(args, cwd=ROOT)
            if done.returncode:
                print(f"reproduce: `{c}` failed (exit {done.returncode})", file=sys.stderr)
                return done.returncode
    return 0


if __name__ == "__main__":
    sys.exit(main())
