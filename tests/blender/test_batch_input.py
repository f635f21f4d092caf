"""The batch run without a .blend (--input), its JSON progress, its help, and the
`blender -c relight` command: scripts/relight_batch.py as a subprocess on the bpy module, and
the registered command's handler called as Blender would call it."""

import hashlib
import json
import math
import pathlib
import shutil
import signal
import subprocess
import sys
import types

import bpy
import numpy as np
import pytest

from conftest import ROOT, write_hdri

SCRIPT = ROOT / "scripts" / "relight_batch.py"


def exr_plate(folder, count=6, start=1001):
    """shot.1001.exr ... : a small float EXR sequence numbered like a VFX plate."""
    from clip_fixtures import ramp_frames, write_exr_sequence

    frames = [f.astype(np.float32) / 255.0 for f in ramp_frames(count, 48, 64)]
    write_exr_sequence(folder, frames, prefix="shot.", start=start)
    return pathlib.Path(folder)


def run(*args, **kw):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True,
                          text=True, timeout=300, cwd=ROOT, **kw)


def digests(folder, pattern):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(pathlib.Path(folder).glob(pattern))}


def lights_blend(path, lamp=True):
    """A .blend with a camera (and a warm key lamp to its right) and nothing to relight."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    cam.location, cam.rotation_euler = (0.0, -3.0, 0.0), (math.pi / 2, 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    if lamp:
        key = bpy.data.objects.new("Key", bpy.data.lights.new("Key", 'POINT'))
        key.data.energy, key.data.color = 300.0, (1.0, 0.8, 0.6)
        key.location = (2.0, -2.0, 0.3)
        scene.collection.objects.link(key)
    bpy.ops.wm.save_as_mainfile(filepath=str(path))
    return path


def test_a_sequence_keeps_its_numbers_and_chunks_equal_one_run(toy_models, tmp_path):
    plate = exr_plate(tmp_path / "plate")
    common = ["--studio", "sunset", "--models", toy_models]
    whole = run("--input", plate, *common, "--out", tmp_path / "whole")
    assert whole.returncode == 0, whole.stderr
    out = tmp_path / "whole" / "shot" / "v001"
    assert f"relit frames are in {out} (relit.1001.exr to relit.1006.exr)" in whole.stdout
    for i, n in enumerate(range(1001, 1007)):  # the pipeline's own frames, under their numbers
        assert (out / f"relit.{n}.exr").samefile(out / "relit" / f"relit_{i:06d}.exr")
    # Farm chunks by scene frame (= the plate's numbers): the same frames, the same names.
    chunks = [subprocess.Popen([sys.executable, str(SCRIPT), "--input", str(plate / f), *map(
        str, common), "--out", str(tmp_path / "chunked"), "--frames", frames], cwd=ROOT,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for f, frames in (("shot.1004.exr", "1001-1003"), ("shot.1001.exr", "1004-1006"))]
    for p in chunks:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
    assert digests(tmp_path / "chunked" / "shot" / "v001", "relit.*.exr") == \
        digests(out, "relit.*.exr")
    assert len(digests(out, "relit.*.exr")) == 6


def test_a_movie_is_numbered_by_scene_frame_in_its_colour_space(toy_models, tmp_path):
    from clip_fixtures import ramp_frames, write_movie

    movie = write_movie(tmp_path / "take.mov", ramp_frames(3, 48, 64))
    done = run("--input", movie, "--hdri", write_hdri(tmp_path / "sky.exr"), "--models",
               toy_models, "--out", tmp_path / "out", "--input-colorspace", "Linear Rec.709",
               "--start-frame", "7", "--matte", "--exposure-mode", "physical")
    assert done.returncode == 0, done.stderr
    out = tmp_path / "out" / "take" / "v001"
    assert sorted(p.name for p in out.glob("*.exr")) == [
        "matte.0007.exr", "matte.0008.exr", "matte.0009.exr",
        "relit.0007.exr", "relit.0008.exr", "relit.0009.exr"]
    identity = json.loads((out / "relight_run.json").read_text())["identity"]
    assert identity["colorspace"] == "Linear Rec.709"
    assert identity["settings"]["exposure_mode"] == "physical"  # --exposure-mode reached the run


def test_lights_from_a_blend_light_the_footage_and_the_file_is_not_saved(toy_models, tmp_path):
    plate = exr_plate(tmp_path / "plate", count=2)
    blend = lights_blend(tmp_path / "lights.blend")
    before = blend.read_bytes()
    lit = run("--input", plate, "--lights-from", blend, "--models", toy_models,
              "--out", tmp_path / "lamp")
    assert lit.returncode == 0, lit.stderr
    assert blend.read_bytes() == before
    assert not list(tmp_path.glob("lights.blend1"))
    studio = run("--input", plate, "--studio", "sunset", "--models", toy_models,
                 "--out", tmp_path / "studio")
    assert studio.returncode == 0, studio.stderr
    ids = [json.loads((tmp_path / d / "shot" / "v001" / "relight_run.json").read_text())["identity"]
           for d in ("lamp", "studio")]
    assert ids[0]["lights_sha256"] != ids[1]["lights_sha256"]  # the lamp lit it, not a default
    # A file with nothing that gives light is refused, naming what it lacks.
    dark = lights_blend(tmp_path / "dark.blend", lamp=False)
    refused = run("--input", plate, "--lights-from", dark, "--models", toy_models,
                  "--out", tmp_path / "dark")
    assert refused.returncode == 1, refused.stdout + refused.stderr
    assert "no world" in refused.stderr and "Traceback" not in refused.stderr


def test_json_progress_is_all_that_goes_to_stdout(toy_models, tmp_path):
    plate = exr_plate(tmp_path / "plate", count=4)
    done = run("--input", plate, "--studio", "city", "--models", toy_models, "--out",
               tmp_path / "out", "--progress", "json")
    assert done.returncode == 0, done.stderr
    events = [json.loads(line) for line in done.stdout.splitlines()]  # every line is JSON
    states = [e["state"] for e in events]
    assert states[0] == "started" and states[-1] == "done"
    assert set(states[1:-1]) <= {"frame"}
    assert all({"frame", "total", "fps", "eta"} <= e.keys() for e in events)
    assert events[-1]["frame"] == events[-1]["total"] == 4
    assert [e["frame"] for e in events] == sorted(e["frame"] for e in events)
    assert "relight_batch: done in" in done.stderr  # the human line moved to stderr
    # The rerun resumes every frame: still started ... done, and nothing else on stdout.
    again = run("--input", plate, "--studio", "city", "--models", toy_models, "--out",
                tmp_path / "out", "--progress", "json")
    assert [json.loads(x)["state"] for x in again.stdout.splitlines()] == ["started", "done"]
    failed = run("--input", plate, "--studio", "city", "--models", toy_models, "--out",
                 tmp_path / "out", "--progress", "json", "--preset", "ultra")
    assert failed.returncode == 1
    (last,) = [json.loads(x) for x in failed.stdout.splitlines()]
    assert last["state"] == "failed" and last["exit"] == 1 and "ultra" in last["message"]
    bad = run("--input", plate, "--progress", "json", "--exposure", "nan")
    assert bad.returncode == 2
    assert [json.loads(x)["exit"] for x in bad.stdout.splitlines()] == [2]


def test_sigterm_is_a_cancel_with_exit_143_said_in_json_and_the_rerun_resumes(toy_models,
                                                                               tmp_path):
    plate = exr_plate(tmp_path / "plate", count=24)
    cmd = [sys.executable, str(SCRIPT), "--input", str(plate), "--studio", "city", "--models",
           str(toy_models), "--out", str(tmp_path / "out"), "--progress", "json"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lines = []
    for line in proc.stdout:
        lines.append(json.loads(line))
        if lines[-1]["state"] == "frame" and lines[-1]["frame"] >= 2:
            proc.send_signal(signal.SIGTERM)  # a farm manager stopping the task
            break
    rest, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, rest + err
    lines += [json.loads(x) for x in rest.splitlines()]
    assert lines[-1]["state"] == "cancelled" and lines[-1]["exit"] == 143
    assert 2 <= lines[-1]["frame"] < 24
    assert "relight_batch: cancelled, run again to resume" in err
    assert not list((tmp_path / "out").rglob("*.lock"))
    resumed = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    started = json.loads(resumed.stdout.splitlines()[0])
    assert started["state"] == "started" and started["frame"] >= 2  # resumed, not redone
    assert len(list((tmp_path / "out" / "shot" / "v001").glob("relit.*.exr"))) == 24


def test_help_shows_both_forms_the_exit_statuses_presets_and_studios(toy_models):
    done = run("--help", "--models", toy_models)
    assert done.returncode == 0, done.stderr
    for text in ("blender -b", "blender -c relight", "--input PATH", "130", "143",
                 "studio HDRIs (--studio): city", "sunset", f"presets (--preset) in {toy_models}",
                 "  toy "):
        assert text in done.stdout, text


# ---- blender -c relight: the handler Blender calls, in this process --------------------------

def test_the_extension_registers_and_unregisters_the_relight_command(extension, monkeypatch):
    batch = extension.ops.batch
    assert batch._cli_handle is not None  # registered for real when the extension registered
    calls = []
    monkeypatch.setattr(bpy.utils, "register_cli_command",
                        lambda name, fn: calls.append(("register", name, fn)) or "handle")
    monkeypatch.setattr(bpy.utils, "unregister_cli_command",
                        lambda handle: calls.append(("unregister", handle)))
    real = batch._cli_handle
    try:
        batch._cli_handle = None
        batch.register()
        batch.unregister()
    finally:
        batch._cli_handle = real
    assert calls == [("register", "relight", batch.cli_command), ("unregister", "handle")]
    assert batch._cli_handle is real


def test_the_command_runs_the_scripts_main_with_its_exit_statuses(extension, toy_models,
                                                                  tmp_path, capfd):
    cli = extension.ops.batch.cli_command
    plate = exr_plate(tmp_path / "plate", count=2)
    assert cli(["--input", str(plate), "--studio", "sunset", "--models", str(toy_models),
                "--out", str(tmp_path / "cli")]) == 0
    script = run("--input", plate, "--studio", "sunset", "--models", toy_models,
                 "--out", tmp_path / "script")
    assert script.returncode == 0, script.stderr
    assert digests(tmp_path / "cli" / "shot" / "v001", "relit.*.exr") == \
        digests(tmp_path / "script" / "shot" / "v001", "relit.*.exr")
    assert len(digests(tmp_path / "cli" / "shot" / "v001", "relit.*.exr")) == 2
    capfd.readouterr()
    assert cli(["--help"]) == 0
    assert "blender -c relight" in capfd.readouterr().out
    cases = [
        (["--input", str(tmp_path / "none.mov"), "--studio", "sunset", "--out", "x"], 1,
         "does not exist"),
        (["--input", str(plate), "--out", "x"], 2, "--input needs lighting"),
        (["--input", str(plate), "--studio", "sunset"], 2, "--input needs --out DIR"),
        (["--input", str(plate), "--studio", "sunset", "--out", "x", "--save"], 2,
         "--save needs a .blend"),
        (["--input", str(plate), "--scene-lights", "--out", "x"], 2, "needs --lights-from"),
        (["--strip", "A", "--lights-from", "l.blend"], 2, "--lights-from goes with --input"),
        (["--input", str(plate), "--studio", "sunset", "--out", str(tmp_path / "o"),
          "--input-colorspace", "Nope", "--models", str(toy_models)], 1,
         "no colour space named 'Nope'"),
        (["--input", str(plate), "--studio", "nowhere", "--out", str(tmp_path / "o"),
          "--models", str(toy_models)], 1, "no studio HDRI named 'nowhere'"),
        (["--strip", "A", "--exposure-mode", "bright"], 2, "invalid choice: 'bright'"),
        (["--demo", "--input", str(plate)], 2, "either --strip NAME or --demo, or --input"),
    ]
    for args, code, message in cases:
        assert cli(args) == code, args
        said = capfd.readouterr()
        assert message in said.err, (args, said.err)
        assert "Traceback" not in said.out + said.err


def test_exposure_mode_and_compression_reach_the_scene_settings(extension):
    batch = extension.ops.batch
    settings = bpy.context.scene.relight
    assert (settings.exposure_mode, settings.exr_compression) == ('KEEP', 'PIZ')  # defaults
    batch.apply_exposure_mode(settings, "physical")
    assert settings.exposure_mode == 'PHYSICAL'
    batch.apply_exposure_mode(settings, None)  # not given: the .blend's setting stays
    assert settings.exposure_mode == 'PHYSICAL'
    args = batch.parse_args(["--demo", "--exr-compression", "zip"])
    batch.apply_settings(bpy.context.scene, args)
    assert settings.exr_compression == 'ZIP'


def test_every_farm_task_is_a_command_line_the_batch_run_accepts(extension, tmp_path):
    """The Flamenco job type (farm/flamenco/relight.js) writes command lines that this very
    parser reads: the chunks and the last task, with every lighting choice."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed; the Flamenco job type is JavaScript")
    sys.path.insert(0, str(ROOT / "tests" / "core"))
    try:
        from test_flamenco_job import compile_job
    finally:
        sys.path.remove(str(ROOT / "tests" / "core"))
    job = compile_job(tmp_path, frames="-2-7", chunk_size=4, studio="sunset", rotation="90",
                      exposure="-1.5", exposure_mode="physical", preset="portrait",
                      write_matte=True)
    batch = extension.ops.batch
    parsed = []
    for task in job["tasks"]:
        argv = ["blender", "-b", "shot.blend", *task["commands"][0]["params"]["args"]]
        parsed.append(batch.parse_args(batch.script_args(argv)))
    assert [a.frames for a in parsed] == [(-2, 1), (2, 5), (6, 7), None]
    assert [a.save for a in parsed] == [False, False, False, True]
    for a in parsed:
        assert (a.strip, a.studio, a.rotation, a.exposure, a.exposure_mode, a.preset, a.matte) \
            == ("Take 1", "sunset", 90.0, -1.5, "physical", "portrait", True)
