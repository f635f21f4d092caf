"""Hard cases (tests/HARD_CASES.md) that need Blender: the relight operator and the batch script
on the bpy module with the toy model. Each test states what must happen: finite frames, or a
non-zero exit with a message and nothing written or replaced."""

import hashlib
import pathlib
import re
import subprocess
import sys

import bpy
import numpy as np
import OpenEXR
import pytest

from conftest import ROOT, footage_scene, write_png_sequence

SCRIPT = ROOT / "scripts" / "relight_batch.py"


def read_exr(path):
    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels, dtype=np.float32)


def write_exr(path, rgb):
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION},
                      {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}) as f:
        f.write(str(path))
    return path


def stamps(folder):
    return {p.name: (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(pathlib.Path(folder).rglob("*")) if p.is_file()}


def test_operator_relights_exr_footage_with_nan_inf_and_negative_pixels(extension, toy_models,
                                                                          tmp_path):
    folder = tmp_path / "plates"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(2):
        px = rng.random((24, 32, 3)).astype(np.float32)
        px[0, :4] = np.array([np.nan, np.inf, -np.inf, -3.0])[:, None]
        px[5:9, 5:9] = np.nan
        write_exr(folder / f"plate.{i + 1:04d}.exr", px)
    before = stamps(folder)
    bpy.ops.relight.import_footage(filepath=str(folder / "plate.0001.exr"), frame_start=1)
    settings = bpy.context.scene.relight
    settings.light_source = 'HDRI_FILE'
    settings.hdri_path = str(write_exr(tmp_path / "sky.exr", np.full((32, 64, 3), 0.5)))
    settings.output_dir = str(tmp_path / "out") + "/"
    assert bpy.ops.relight.relight_strip(models_dir=str(toy_models)) == {'FINISHED'}
    relit = sorted((tmp_path / "out").rglob("relit_*.exr"))
    assert len(relit) == 2
    for f in relit:
        px = read_exr(f)
        assert px.shape == (24, 32, 3) and np.all(np.isfinite(px)) and px.min() >= 0
    assert stamps(folder) == before  # the footage is never touched


def save_scene(tmp_path, count=3):
    strip = footage_scene(tmp_path, count=count, frame_start=1)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    return blend, strip.name


def batch(blend, strip, toy_models, out, *extra):
    return subprocess.run([sys.executable, str(SCRIPT), str(blend), "--strip", strip, "--models",
                           str(toy_models), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)


def test_batch_hdri_with_a_1e5_sun_and_bad_texels_gives_finite_frames(extension, toy_models,
                                                                      tmp_path):
    """A sun of 1e5 plus NaN, infinite and negative texels: the bad texels count as black with a
    warning; every frame is finite (values past the half range clamp to 65504)."""
    blend, strip = save_scene(tmp_path)
    sky = np.full((32, 64, 3), 0.2, np.float32)
    sky[15, 48] = 1e5  # u = 0.75, the horizon: toward the camera of an unrotated scene
    sky[2, 3], sky[4, 5], sky[6, 7] = np.nan, np.inf, -1.0
    done = batch(blend, strip, toy_models, tmp_path / "out", "--hdri",
                 str(write_exr(tmp_path / "sun.exr", sky)))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "treated as black" in done.stdout + done.stderr
    relit = sorted((tmp_path / "out").rglob("relit_*.exr"))
    assert len(relit) == 3
    for f in relit:
        px = read_exr(f)
        assert np.all(np.isfinite(px)) and 0 <= px.min() and px.max() <= 65504


def test_batch_rerun_never_replaces_another_take_unless_asked(extension, toy_models, tmp_path):
    """Another lighting into the same output folder makes a new take and leaves the first as it
    was; with --overwrite it replaces the latest take's frames. Lighting that an exposure of -100
    makes black exits 1 before anything is touched, even with --overwrite."""
    blend, strip = save_scene(tmp_path)
    out = tmp_path / "out"
    first = batch(blend, strip, toy_models, out, "--exposure-mode", "physical")
    assert first.returncode == 0, first.stderr
    take1 = stamps(out / strip / "v001")
    second = batch(blend, strip, toy_models, out, "--exposure-mode", "physical", "--exposure", "1")
    assert second.returncode == 0, second.stderr
    assert f"relit frames are in {out / strip / 'v002'}" in second.stdout
    assert stamps(out / strip / "v001") == take1
    before, take2 = stamps(out), stamps(out / strip / "v002")
    black = batch(blend, strip, toy_models, out, "--exposure", "-100", "--overwrite")
    assert black.returncode == 1, black.stdout + black.stderr
    assert "The lighting is black: the HDRI is black" in black.stderr
    assert "The exposure -100 darkens any light" in black.stderr
    assert "Traceback" not in black.stderr
    assert stamps(out) == before
    replaced = batch(blend, strip, toy_models, out, "--exposure-mode", "physical", "--exposure",
                     "2", "--overwrite")
    assert replaced.returncode == 0, replaced.stderr
    assert sorted(p.name for p in (out / strip).iterdir()) == ["v001", "v002"]
    assert stamps(out / strip / "v001") == take1
    assert stamps(out / strip / "v002") != take2
    assert len(sorted((out / strip / "v002").rglob("relit_*.exr"))) == 3


def _lamp(name, energy, location=(0.0, -3.0, 0.0)):
    lamp = bpy.data.objects.new(name, bpy.data.lights.new(name, 'POINT'))
    lamp.data.energy = energy
    lamp.location = location
    bpy.context.scene.collection.objects.link(lamp)
    return lamp


def test_black_or_nan_scene_lighting_is_refused_saying_what_to_set(extension, toy_models,
                                                                   tmp_path):
    """No world and only a 0 W lamp, a black world, or a lamp whose energy is NaN: the operator
    reports what the scene lacks or which lamp is broken, before anything is written."""
    footage_scene(tmp_path, count=2)
    scene, settings = bpy.context.scene, bpy.context.scene.relight
    subject = bpy.data.objects.new("Subject", None)
    scene.collection.objects.link(subject)
    settings.subject = subject
    settings.light_source = 'WORLD_AND_LAMPS'
    scene.world = None
    _lamp("Key", 0.0)
    relight = lambda: bpy.ops.relight.relight_strip(models_dir=str(toy_models))  # noqa: E731
    with pytest.raises(RuntimeError, match="the scene has no world and no lamps with energy.*"
                                           "Add a lamp with energy or a world HDRI"):
        relight()
    settings.light_source = 'WORLD'
    scene.world = bpy.data.worlds.new("Night")
    scene.world.color = (0.0, 0.0, 0.0)
    if scene.world.node_tree is not None:  # Blender 5 worlds have nodes from the start
        scene.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    with pytest.raises(RuntimeError, match="the world 'Night' gives no light"):
        relight()
    settings.light_source = 'LAMPS'
    _lamp("Fill", float("nan"))
    with pytest.raises(RuntimeError, match="Lamp 'Fill': its energy is not a finite number"):
        relight()
    assert not (tmp_path / "out").exists()
    bpy.data.objects["Fill"].data.energy = 100.0  # a lamp with energy lights the subject
    for name, value, match in (("exposure", 2000.0, "exposure is 2000 on frame 1"),
                               ("rotation", float("nan"), "rotation is nan on frame 1")):
        setattr(settings, name, value)  # the panel's properties have no hard limits
        with pytest.raises(RuntimeError, match=match):
            relight()
        setattr(settings, name, 0.0)
    assert not (tmp_path / "out").exists()
    assert relight() == {'FINISHED'}
    assert len(list((tmp_path / "out").rglob("relit_*.exr"))) == 2


def test_strips_whose_names_share_a_slug_never_share_a_folder(extension, toy_models, tmp_path):
    """'顔' and '名前' (no ASCII at all), 'a b' and 'a_b': each strip gets its own folder, so
    Overwrite on one never deletes another's frames."""
    first = footage_scene(tmp_path, count=2)
    files = write_png_sequence(tmp_path / "other", count=2, prefix="other_")
    bpy.ops.relight.import_footage(filepath=str(files[0]), frame_start=1)
    second = bpy.context.scene.sequence_editor.active_strip
    assert second != first
    out = tmp_path / "out"

    def relight(strip):
        return bpy.ops.relight.relight_strip(strip=strip.name, models_dir=str(toy_models))

    for a, b in (("顔", "名前"), ("a b", "a_b")):
        first.name, second.name = a, b
        assert relight(first) == {'FINISHED'} and relight(second) == {'FINISHED'}
    folders = sorted(p.name for p in out.iterdir())
    assert len(folders) == 4 and "a_b" in folders, folders
    assert all(len(list((out / f / "v001" / "relit").glob("relit_*.exr"))) == 2 for f in folders)
    before = {f: stamps(out / f) for f in folders}
    settings = bpy.context.scene.relight
    settings.exposure, settings.overwrite = 1.0, True
    assert relight(second) == {'FINISHED'}  # 'a_b' replaced under other lighting
    after = {f: stamps(out / f) for f in folders}
    assert after["a_b"] != before["a_b"]
    assert {f: v for f, v in after.items() if f != "a_b"} == \
        {f: v for f, v in before.items() if f != "a_b"}


def test_bad_frames_are_named_by_file_and_scene_frame(extension, toy_models, tmp_path):
    """A frame of another size and a damaged frame: the message names the file and the frame
    as the timeline shows it, and says what to do."""
    footage_scene(tmp_path, count=4, frame_start=10)
    odd = write_png_sequence(tmp_path / "footage", count=1, size=(32, 32), start=3)[0]
    relight = lambda: bpy.ops.relight.relight_strip(models_dir=str(toy_models))  # noqa: E731
    path = re.escape(str(odd))
    with pytest.raises(RuntimeError, match=rf"Scene frame 12 \({path}\) is 32x32, but the clip "
                                           r"is 64x64.*Re-export the sequence at one size"):
        relight()
    odd.write_bytes(b"not a png at all")
    with pytest.raises(RuntimeError, match=rf"Scene frame 12: Cannot read the image {path} .*"
                                           "replace it with an intact copy"):
        relight()
