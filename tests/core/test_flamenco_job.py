"""The Flamenco job type (farm/flamenco/relight.js), run by node with a fake Flamenco `author` API."""

import json
import pathlib
import re
import shutil
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
JOB_JS = ROOT / "farm" / "flamenco" / "relight.js"

# Loads the job type into a sandbox with the globals Flamenco's Manager provides, runs compileJob
# and prints what it authored (or the error it threw) as JSON. frameChunker follows the Manager's
# own (internal/manager/job_compilers/js_globals.go, jsFrameChunker): frames and ranges 'A-B' or
# 'A..B' separated by commas, chunks of at most chunkSize frames in regular notation, runs of two
# frames written 'A,B'; '-' always separates, so a negative frame is an invalid range.
HARNESS = r"""
const vm = require("vm");
const fs = require("fs");
const [jsPath, settingsJson, mode] = process.argv.slice(2);
function frameChunker(frameRange, chunkSize) {
  if (mode === "chunker-fails") throw "the Manager's frameChunker was called";
  frameRange = String(frameRange).trim();
  if (frameRange === "") throw `invalid range "${frameRange}": empty range`;
  if (!(chunkSize >= 1)) throw `invalid chunk size, must be positive number: ${chunkSize}`;
  const int = (s) => {
    if (!/^[+-]?\d+$/.test(s.trim())) throw `invalid range "${frameRange}": ${s}`;
    return parseInt(s, 10);
  };
  const set = new Set();
  for (const part of frameRange.split("..").join("-").split(",")) {
    const se = part.split("-");
    if (se.length === 1) set.add(int(se[0]));
    else if (se.length === 2) { for (let f = int(se[0]); f <= int(se[1]); f++) set.add(f); }
    else throw `invalid range "${frameRange}": ${part}`;
  }
  const frames = [...set].sort((a, b) => a - b);
  if (frames.length === 0) throw `invalid range "${frameRange}": empty range`;
  const merge = (fs) => {
    const out = [];
    let a = fs[0], p = fs[0];
    const put = (x, y) => { if (x === y) out.push(`${x}`); else if (x + 1 === y) out.push(`${x}`, `${y}`);
                            else out.push(`${x}-${y}`); };
    for (const f of fs.slice(1)) { if (f > p + 1) { put(a, p); a = f; } p = f; }
    put(a, p);
    return out.join(",");
  };
  const chunks = [];
  for (let i = 0; i < frames.length; i += chunkSize) chunks.push(merge(frames.slice(i, i + chunkSize)));
  return chunks;
}
if (mode === "chunker") {
  const [range, size] = JSON.parse(settingsJson);
  try { console.log(JSON.stringify(frameChunker(range, size))); }
  catch (e) { console.log(JSON.stringify({ error: String(e) })); }
  process.exit(0);
}
const tasks = [];
const author = {
  Task: (name, type) => ({ name, type, commands: [], dependsOn: [],
                           addCommand(c) { this.commands.push(c); },
                           addDependency(t) { this.dependsOn.push(t.name); } }),
  Command: (type, params, totalFrames) => ({ type, params, totalFrames }),
};
const job = { settings: JSON.parse(settingsJson), addTask: (t) => tasks.push(t) };
const sandbox = { author, frameChunker, print: () => {}, job, result: null };
vm.createContext(sandbox);
vm.runInContext(fs.readFileSync(jsPath, "utf8") +
  "\ntry { compileJob(job); result = { jobType: JOB_TYPE }; }" +
  " catch (e) { result = { error: String(e) }; }", sandbox);
console.log(JSON.stringify({ ...sandbox.result, tasks }));
"""


def node_or_skip():
    if shutil.which("node") is None:
        pytest.skip("node is not installed; the Flamenco job type is JavaScript")


def node(tmp_path, *args):
    node_or_skip()
    harness = tmp_path / "harness.js"
    harness.write_text(HARNESS)
    out = subprocess.run(["node", str(harness), str(JOB_JS), *args], check=True,
                         capture_output=True, text=True, timeout=60)
    return json.loads(out.stdout)


def compile_job(tmp_path, mode="", **settings):
    base = {"blendfile": "/farm/shot.blend", "strip": "Take 1", "frames": "1-100",
            "chunk_size": 25, "output_dir": "/farm/relit", "relight_script": "{relight_batch}"}
    base.update(settings)
    return node(tmp_path, json.dumps(base), mode)


def chunk_tasks(result):
    return [t for t in result["tasks"] if t["name"].startswith("relight-")]


def chunk_frames(task):
    args = task["commands"][0]["params"]["args"]
    first, last = map(int, re.fullmatch(r"(-?\d+)-(-?\d+)", args[args.index("--frames") + 1]).groups())
    return list(range(first, last + 1))


@pytest.mark.parametrize("frames,size,chunks", [
    # The Manager's own cases (js_globals_test.go).
    ("1..10,20..25,40,3..8", 4, ["1-4", "5-8", "9,10,20,21", "22-25", "40"]),
    (" 1  .. 10,\t20..25\n,40   ", 4, ["1-4", "5-8", "9,10,20,21", "22-25", "40"]),
    ("47", 4, ["47"]), ("1-3", 3, ["1-3"]),
    ("-3-4", 3, {"error": 'invalid range "-3-4": -3-4'}), ("   ", 4, {"error": "empty range"})])
def test_the_harness_chunks_like_the_flamenco_manager(tmp_path, frames, size, chunks):
    got = node(tmp_path, json.dumps([frames, size]), "chunker")
    if isinstance(chunks, dict):
        assert chunks["error"] in got["error"]
    else:
        assert got == chunks


@pytest.mark.parametrize("frames,chunk,start,end", [
    ("1-100", 25, 1, 100), ("7-30", 5, 7, 30), ("-3-4", 3, -3, 4), ("12", 10, 12, 12),
    ("1-250", 1000, 1, 250), ("5-9", 1, 5, 9), (" 2 - 11 ", 4, 2, 11), ("1-27", 25, 1, 27)])
def test_chunks_cover_the_range_exactly_once(tmp_path, frames, chunk, start, end):
    result = compile_job(tmp_path, frames=frames, chunk_size=chunk)
    assert "error" not in result
    covered = [f for t in chunk_tasks(result) for f in chunk_frames(t)]
    expected = list(range(start, end + 1))
    assert sorted(covered) == expected          # every frame ...
    assert len(covered) == len(set(covered))    # ... exactly once
    assert all(len(chunk_frames(t)) <= chunk for t in chunk_tasks(result))
    assert len(chunk_tasks(result)) == -(-(end - start + 1) // chunk)


def test_the_chunks_come_from_flamencos_frame_chunker(tmp_path):
    result = compile_job(tmp_path, mode="chunker-fails")
    assert result["tasks"] == []
    assert result["error"] == "the Manager's frameChunker was called"
    # A two-frame chunk comes back as "26,27" and is one task for frames 26-27.
    result = compile_job(tmp_path, frames="1-27", chunk_size=25)
    assert [t["name"] for t in chunk_tasks(result)] == ["relight-1-25", "relight-26-27"]


def test_task_runs_the_batch_script_on_the_blend_file(tmp_path):
    result = compile_job(tmp_path, frames="1-10", chunk_size=10, hdri="/hdri/studio.exr",
                         preset="fast", write_matte=True)
    task, finish = result["tasks"]
    assert task["type"] == "blender" and task["name"] == "relight-1-10"
    cmd = task["commands"][0]
    assert cmd["type"] == "blender-render" and cmd["totalFrames"] == 10
    params = cmd["params"]
    assert params["blendfile"] == "/farm/shot.blend"
    run_args = ["--python", "{relight_batch}", "--", "--strip", "Take 1", "--out", "/farm/relit",
                "--hdri", "/hdri/studio.exr", "--preset", "fast", "--matte"]
    assert params["args"] == run_args + ["--frames", "1-10"]
    # Last: the same run over the whole strip (nothing left to do), adding the strip and saving.
    assert finish["name"] == "add-relit-strip" and finish["type"] == "blender"
    assert finish["dependsOn"] == ["relight-1-10"]
    last = finish["commands"][0]
    assert last["type"] == "blender-render" and last["params"]["blendfile"] == "/farm/shot.blend"
    assert last["params"]["args"] == run_args + ["--save"]


def test_the_last_task_waits_for_every_chunk_and_can_be_left_out(tmp_path):
    result = compile_job(tmp_path, frames="1-100", chunk_size=30)
    *chunks, finish = result["tasks"]
    assert finish["dependsOn"] == [t["name"] for t in chunks] and len(chunks) == 4
    result = compile_job(tmp_path, frames="1-100", chunk_size=30, add_strip=False)
    assert [t["name"] for t in result["tasks"]] == [t["name"] for t in chunks]


def test_scene_lights_flag_and_defaults(tmp_path):
    result = compile_job(tmp_path, frames="3-4", scene_lights=True)
    args = result["tasks"][0]["commands"][0]["params"]["args"]
    assert "--scene-lights" in args and "--hdri" not in args and "--preset" not in args
    for flag in ("--rotation", "--exposure", "--exposure-mode", "--studio", "--world"):
        assert flag not in args
    keys = {s["key"] for s in result["jobType"]["settings"]}
    assert {"blendfile", "strip", "frames", "chunk_size", "output_dir", "hdri", "studio",
            "scene_lights", "world", "rotation", "exposure", "exposure_mode", "preset"} <= keys


@pytest.mark.parametrize("settings,flags", [
    ({"studio": "sunset"}, ["--studio", "sunset"]),
    ({"world": True}, ["--world"]),
    ({"rotation": "90", "exposure": " -1.5 "}, ["--rotation", "90", "--exposure", "-1.5"]),
    ({"rotation": 45.5, "exposure": 0}, ["--rotation", "45.5", "--exposure", "0"]),
    ({"rotation": "", "exposure": ""}, []),
    ({"exposure_mode": "physical"}, ["--exposure-mode", "physical"]),
    ({"exposure_mode": "keep", "preset": "portrait"},
     ["--preset", "portrait", "--exposure-mode", "keep"]),
    ({"exposure_mode": "blend"}, []),
])
def test_lighting_settings_become_the_scripts_flags(tmp_path, settings, flags):
    result = compile_job(tmp_path, frames="1-4", **settings)
    for task in result["tasks"]:  # every task, the last one too: one run
        args = task["commands"][0]["params"]["args"]
        after_out = args[args.index("/farm/relit") + 1:]
        assert [a for a in after_out if a not in ("--frames", "1-4", "--save")] == flags


@pytest.mark.parametrize("settings,message", [
    ({"hdri": "/sky.exr", "studio": "sunset"}, "choose one lighting"),
    ({"scene_lights": True, "world": True}, "choose one lighting"),
    ({"rotation": "ten"}, "rotation must be a number of degrees"),
    ({"exposure": "1e9"}, "exposure must be a number of stops"),
    ({"exposure_mode": "bright"}, "exposure_mode must be"),
])
def test_contradictory_or_absurd_settings_are_refused_at_submission(tmp_path, settings, message):
    result = compile_job(tmp_path, frames="1-4", **settings)
    assert result["tasks"] == []
    assert message in result["error"]


@pytest.mark.parametrize("frames", ["10-1", "1-", "a-b", ""])
def test_bad_frame_ranges_are_refused(tmp_path, frames):
    result = compile_job(tmp_path, frames=frames)
    assert result["tasks"] == []
    assert "frames" in result["error"]
