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


def relit_digests(out, strip, take="v001"):
    folder = pathlib.Path(out) / strip / take / "relit"
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
    # Obvious nonsense is a bad argument, said before anything is opened.
    (["{blend}", "--strip", "{strip}", "--exposure", "2000"], 2,
     "--exposure must be a finite number of stops between -128 and 128, got '2000'"),
    (["{blend}", "--strip", "{strip}", "--exposure", "inf"], 2, "got 'inf'"),
    (["{blend}", "--strip", "{strip}", "--rotation", "nan"], 2,
     "--rotation must be a finite number of degrees"),
    (["{blend}", "--strip", "{strip}", "--rotation", "ten"], 2, "'ten' is not a number"),
    # Inputs that crashed the run: now a user error, one line.
    (["{blend}", "--strip", "{strip}", "--models", "{models}", "--hdri", "{tmp}/huge.hdr"], 1,
     "claims 1000000x1000000 pixels"),
    (["{blend}", "--strip", "{strip}", "--models", "{tmp}/deep"], 1, "nested too deeply"),
])
def test_failures_exit_non_zero_with_a_message(extension, toy_models, tmp_path, args, code,
                                               message):
    blend, strip = save_scene(tmp_path, count=2)
    (tmp_path / "huge.hdr").write_bytes(b"#?RADIANCE\n\n-Y 1000000 +X 1000000\n" + bytes(64))
    deep = tmp_path / "deep"
    deep.mkdir()
    for f in toy_models.iterdir():
        (deep / f.name).write_bytes(f.read_bytes())
    next(deep.glob("*.json")).write_text("[" * 100_000 + "]" * 100_000)
    names = dict(blend=blend, strip=strip, models=toy_models, tmp=tmp_path)
    done = run([sys.executable, str(SCRIPT), *(a.format(**names) for a in args)])
    assert done.returncode == code, done.stdout + done.stderr
    assert message in done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    assert not list(tmp_path.glob("**/relit_*.exr"))


def test_blender_style_arguments_after_double_dash(extension):
    batch = extension.ops.batch  # the code the script and `blender -c relight` both run
    argv = ["blender", "-b", "shot.blend", "-P", "relight_batch.py", "--", "--strip", "A",
            "--frames", "10-20"]
    args = batch.parse_args(batch.script_args(argv))
    assert (args.strip, args.frames, args.blend) == ("A", (10, 20), None)
    assert batch.script_args(["relight_batch.py", "s.blend", "--demo"]) == ["s.blend", "--demo"]
    for text, frames in (("-10--5", (-10, -5)), ("-3-4", (-3, 4)), ("-7", (-7, -7))):
        assert batch.parse_args(["--strip", "A", "--frames", text]).frames == frames


def test_background_choices_are_the_pipelines(extension):
    """The batch run spells the choices out (importing the pipeline to read them would load it
    whenever the extension registers); they must stay the pipeline's (and the panel's) list."""
    from portrait_relight.addon import pipeline

    batch = extension.ops.batch
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
    relit = list((tmp_path / "demo").glob("*/v001/relit/relit_*.exr"))
    assert len(relit) == len(frames)
    assert "relit frames are in" in done.stdout


@pytest.mark.parametrize("flags,want", [(["--keep-background"], {"background": "keep"}),
                                        (["--background", "relit"], {"background": "relit"})])
def test_background_flags_reach_the_run(toy_models, tmp_path, flags, want):
    if not sorted((ROOT / "demo" / "frames").glob("*.png")):
        pytest.skip("the demo clip (demo/frames) has not been made in this checkout")
    done = run([sys.executable, str(SCRIPT), "--demo", "--models", str(toy_models), "--out",
                str(tmp_path / "demo"), *flags, "--frames", "1-2"])
    assert done.returncode == 0, done.stderr
    (run_file,) = (tmp_path / "demo").glob("*/v001/relight_run.json")
    settings = json.loads(run_file.read_text())["identity"]["settings"]
    assert {k: settings[k] for k in want} == want


def failing_models(folder):
    """A model that loads and passes every check but fails inside onnxruntime when run (a
    Reshape to an impossible shape): an error the add-on does not expect, so a bug to report."""
    import numpy as np
    from onnx import helper

    sys.path.insert(0, str(ROOT))  # the core tests' model builders
    try:
        from tests.onnx_fixtures import card_fields, graph_model, save_model
    finally:
        sys.path.remove(str(ROOT))
    nodes = [helper.make_node("Reshape", ["image", "bad"], ["r"]),
             helper.make_node("Identity", ["image"], ["relit"]),
             helper.make_node("Identity", ["target_light"], ["source_light"]),
             helper.make_node("Concat", ["r", "r"], ["parsing"], axis=1)]
    model = graph_model(nodes, {"bad": np.array([1, 7, -1, 5], np.int64)}, "fails")
    save_model(model, folder, "fails", card_fields(stride=1, working=64))
    return folder


def test_an_unexpected_error_is_one_line_and_exit_3_with_its_traceback_only_on_demand(
        extension, tmp_path):
    """A bug inside the operator: exit 3 and one line; its traceback once with --debug. (Left
    to Blender, the operator's traceback was printed, then handed to the script as the error's
    text and printed again, with exit 1 as if it were a user error.)"""
    blend, strip = save_scene(tmp_path, count=2)
    models = failing_models(tmp_path / "models")
    cmd = [sys.executable, str(SCRIPT), str(blend), "--strip", strip, "--models", str(models),
           "--out", str(tmp_path / "out")]
    done = run(cmd)
    assert done.returncode == 3, done.stdout + done.stderr
    said = [line for line in done.stderr.splitlines() if line.startswith("relight_batch:")]
    assert len(said) == 1 and said[0].startswith("relight_batch: unexpected error (Fail: ")
    assert said[0].endswith("rerun with --debug for the traceback and report it")
    assert "Traceback" not in done.stdout + done.stderr
    debug = run(cmd + ["--debug"])
    assert debug.returncode == 3
    assert (debug.stdout + debug.stderr).count("Traceback (most recent call last)") == 1
    assert "in execute" in debug.stderr  # where the bug is: inside the operator
    assert not list((tmp_path / "out").rglob("*.lock"))


def test_ctrl_c_cancels_in_one_line_with_exit_130_and_the_rerun_resumes(extension, toy_models,
                                                                       tmp_path):
    blend, strip = save_scene(tmp_path, count=24)
    whole = run(batch_cmd(blend, strip, toy_models, tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr
    proc = subprocess.Popen(batch_cmd(blend, strip, toy_models, tmp_path / "out"), cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        m = re.match(r"relight: (\d+)/24 frames", line)
        if m and int(m.group(1)) >= 2:
            proc.send_signal(signal.SIGINT)  # Ctrl-C
            break
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, out + err
    assert err.strip() == "relight_batch: cancelled, run again to resume"
    assert "Traceback" not in out + err and "KeyboardInterrupt" not in out + err
    partial = relit_digests(tmp_path / "out", strip)
    assert 2 <= len(partial) < 24
    assert not list((tmp_path / "out").rglob("*.lock"))  # the folder was released
    resumed = run(batch_cmd(blend, strip, toy_models, tmp_path / "out"))
    assert resumed.returncode == 0, resumed.stderr
    assert relit_digests(tmp_path / "out", strip) == relit_digests(tmp_path / "whole", strip)


def test_a_take_in_use_by_another_run_is_never_replaced_under_it(extension, toy_models,
                                                                 tmp_path):
    """Another run is writing the strip's take v001: a run of other lighting makes take v002
    beside it; asked to replace the latest take, it is refused naming the holder."""
    blend, strip = save_scene(tmp_path, count=2)
    take = tmp_path / "out" / strip / "v001"
    take.mkdir(parents=True)
    (take / "take.json").write_text(json.dumps({"run": "another-run"}))
    hold = ("import sys\nfrom addon import runlock\n"
            "with runlock.FolderLock(sys.argv[1], 'another-run') as lock:\n"
            "    lock.end_setup()\n    print('held', flush=True)\n    sys.stdin.read()\n")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(take)], cwd=ROOT,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)), stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        done = run(batch_cmd(blend, strip, toy_models, tmp_path / "out", "--overwrite"))
        assert done.returncode == 1, done.stdout + done.stderr
        assert "is still being written by another relight run" in done.stderr
        assert f"process {holder.pid} on " in done.stderr
        assert "Traceback" not in done.stderr
        assert not list(take.rglob("relit_*.exr"))
        done = run(batch_cmd(blend, strip, toy_models, tmp_path / "out"))
        assert done.returncode == 0, done.stdout + done.stderr
        assert f"relit frames are in {take.with_name('v002')}" in done.stdout
        assert not list(take.rglob("relit_*.exr"))
    finally:
        holder.stdin.close()
        holder.wait(timeout=60)
    assert run(batch_cmd(blend, strip, toy_models, tmp_path / "out",
                         "--overwrite")).returncode == 0  # v002 is free: resumed, all done


def test_the_operator_reports_a_bug_once_and_keeps_it_for_scripts(extension, tmp_path, capfd):
    footage_scene(tmp_path, count=2)
    models = failing_models(tmp_path / "models")
    with pytest.raises(RuntimeError) as err:
        bpy.ops.relight.relight_strip(models_dir=str(models))
    text = str(err.value).strip()
    assert text.startswith("Error: Unexpected error (Fail: ") and "\n" not in text
    assert "Traceback" not in text
    printed = capfd.readouterr()
    assert (printed.out + printed.err).count("Traceback (most recent call last)") == 1
    assert type(extension.ops.relight_strip.last_error).__name__ == "Fail"
    assert not list((tmp_path / "out").rglob("*.lock"))
