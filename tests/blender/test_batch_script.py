"""scripts/relight_batch.py as a subprocess with plain python on the bpy module: farm chunks,
a real kill half-way, and clear failures."""

import hashlib
import json
import os
import pathlib
import re
import signal
import subprocess
import sys

import bpy
import pytest

from conftest import ROOT, footage_scene

SCRIPT = ROOT / "scripts" / "relight_batch.py"


def save_scene(tmp_path, count=8):
    strip = footage_scene(tmp_path, count=count, frame_start=1)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend, strip.name


def batch_cmd(blend, strip, toy_models, out, *extra):
    return [sys.executable, str(SCRIPT), str(blend), "--strip", strip, "--models",
            str(toy_models), "--out", str(out), *extra]


def run(cmd, **kw):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT, **kw)


def relit_digests(out, strip):
    folder = pathlib.Path(out) / strip / "relit"
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.glob("relit_*.exr"))}


def test_two_concurrent_chunks_equal_one_run(extension, toy_models, tmp_path):
    blend, strip = save_scene(tmp_path, count=8)
    whole = run(batch_cmd(blend, strip, toy_models, tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    assert "8/8 frames" in whole.stdout
    chunks = [subprocess.Popen(batch_cmd(blend, strip, toy_models, tmp_path / "chunked",
                                         "--frames", frames),
                               cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
              for frames in ("1-4", "5-8")]
    for p in chunks:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    expected = relit_digests(tmp_path / "whole", strip)
    assert len(expected) == 8
    assert relit_digests(tmp_path / "chunked", strip) == expected


def test_killed_run_resumes_to_identical_output(extension, toy_models, tmp_path):
    blend, strip = save_scene(tmp_path, count=24)
    whole = run(batch_cmd(blend, strip, toy_models, tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    killed = subprocess.Popen(batch_cmd(blend, strip, toy_models, tmp_path / "killed"),
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                              text=True)
    for line in killed.stdout:
        m = re.match(r"relight: (\d+)/24 frames", line)
        if m and int(m.group(1)) >= 2:             # progress may skip numbers: frames overlap
            os.kill(killed.pid, signal.SIGKILL)    # a real kill, mid-run, no clean-up
            break
    killed.wait(timeout=60)
    assert killed.returncode == -signal.SIGKILL
    partial = relit_digests(tmp_path / "killed", strip)
    assert 2 <= len(partial) < 24, "the kill must land half-way for this test to mean anything"
    resumed = run(batch_cmd(blend, strip, toy_models, tmp_path / "killed"))
    assert resumed.returncode == 0, resumed.stderr
    assert "resumed" in resumed.stdout.lower()
    # Every finished frame is byte-identical to the uninterrupted run's, and the temporary files
    # the killed process was writing are swept when the run resumes (their writer is dead).
    assert relit_digests(tmp_path / "killed", strip) == relit_digests(tmp_path / "whole", strip)
    assert not list((tmp_path / "killed").rglob("*.partial"))


@pytest.mark.parametrize("args,code,message", [
    (["{blend}", "--strip", "Nope", "--models", "{models}"], 1, "no strip named 'Nope'"),
    (["{blend}", "--strip", "x", "--frames", "9-1"], 2, "ends before it starts"),
    (["{blend}", "--demo", "--strip", "x"], 2, "either --strip NAME or --demo"),
    (["{tmp}/missing.blend", "--strip", "x"], 1, "does not exist"),
    (["--demo", "--models", "{tmp}/empty"], 1, "No trained model is installed"),
    (["{blend}", "--strip", "{strip}", "--models", "{models}", "--preset", "ultra"], 1,
     "No model for the quality preset 'ultra'"),
    (["{blend}", "--strip", "{strip}", "--models", "{tmp}/empty"], 1,
     "No relighting model is installed"),
    (["{blend}", "--strip", "{strip}", "--models", "{models}", "--hdri", "{tmp}/no.exr"], 1,
     "no.exr"),
])
def test_failures_exit_non_zero_with_a_message(extension, toy_models, tmp_path, args, code,
                                               message):
    blend, strip = save_scene(tmp_path, count=2)
    names = dict(blend=blend, strip=strip, models=toy_models, tmp=tmp_path)
    done = run([sys.executable, str(SCRIPT), *(a.format(**names) for a in args)])
    assert done.returncode == code, done.stdout + done.stderr
    assert message in done.stderr
    assert "Traceback" not in done.stderr
    assert not list(tmp_path.glob("**/relit_*.exr"))


def test_blender_style_arguments_after_double_dash():
    import importlib.util

    spec = importlib.util.spec_from_file_location("relight_batch", SCRIPT)
    batch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(batch)
    argv = ["blender", "-b", "shot.blend", "-P", "relight_batch.py", "--", "--strip", "A",
            "--frames", "10-20"]
    args = batch.parse_args(batch.script_args(argv))
    assert (args.strip, args.frames, args.blend) == ("A", (10, 20), None)
    assert batch.script_args(["relight_batch.py", "s.blend", "--demo"]) == ["s.blend", "--demo"]


def test_background_choices_are_the_pipelines(extension):
    """The script parses its flags before the extension loads, so it spells the choices out; they
    must stay the pipeline's (and the panel's) list."""
    import importlib.util

    from portrait_relight.addon import pipeline

    spec = importlib.util.spec_from_file_location("relight_batch", SCRIPT)
    batch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(batch)
    for choice in pipeline.BACKGROUNDS:
        assert batch.parse_args(["--demo", "--background", choice]).background == choice
    with pytest.raises(SystemExit):
        batch.parse_args(["--demo", "--background", "transparent"])
    items = bpy.context.scene.relight.bl_rna.properties["background"].enum_items
    assert sorted(i.identifier.lower() for i in items) == sorted(pipeline.BACKGROUNDS)


def test_demo_relights_the_built_in_clip(toy_models, tmp_path):
    frames = sorted((ROOT / "demo" / "frames").glob("*.png"))
    if not frames:
        pytest.skip("the demo clip (demo/frames) has not been made in this checkout")
    done = run([sys.executable, str(SCRIPT), "--demo", "--models", str(toy_models), "--out",
                str(tmp_path / "demo")])
    assert done.returncode == 0, done.stderr
    relit = list((tmp_path / "demo").glob("*/relit/relit_*.exr"))
    assert len(relit) == len(frames)
    assert "relit frames are in" in done.stdout


@pytest.mark.parametrize("flags,want", [(["--keep-background"], {"keep_background": True}),
                                        (["--background", "relit"], {"background": "relit"})])
def test_background_flags_reach_the_run(toy_models, tmp_path, flags, want):
    if not sorted((ROOT / "demo" / "frames").glob("*.png")):
        pytest.skip("the demo clip (demo/frames) has not been made in this checkout")
    done = run([sys.executable, str(SCRIPT), "--demo", "--models", str(toy_models), "--out",
                str(tmp_path / "demo"), *flags, "--frames", "1-2"])
    assert done.returncode == 0, done.stderr
    (run_file,) = (tmp_path / "demo").glob("*/relight_run.json")
    settings = json.loads(run_file.read_text())["identity"]["settings"]
    assert {k: settings[k] for k in want} == want
