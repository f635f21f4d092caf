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
# and prints what it authored (or the error it threw) as JSON.
HARNESS = r"""
const vm = require("vm");
const fs = require("fs");
const [jsPath, settingsJson] = process.argv.slice(2);
const tasks = [];
const author = {
  Task: (name, type) => ({ name, type, commands: [], addCommand(c) { this.commands.push(c); } }),
  Command: (type, params, totalFrames) => ({ type, params, totalFrames }),
};
const job = { settings: JSON.parse(settingsJson), addTask: (t) => tasks.push(t) };
const sandbox = { author, print: () => {}, job, result: null };
vm.createContext(sandbox);
vm.runInContext(fs.readFileSync(jsPath, "utf8") +
  "\ntry { compileJob(job); result = { jobType: JOB_TYPE }; }" +
  " catch (e) { result = { error: String(e) }; }", sandbox);
console.log(JSON.stringify({ ...sandbox.result, tasks }));
"""


def compile_job(tmp_path, **settings):
    if shutil.which("node") is None:
        pytest.skip("node is not installed; the Flamenco job type is JavaScript")
    harness = tmp_path / "harness.js"
    harness.write_text(HARNESS)
    base = {"blendfile": "/farm/shot.blend", "strip": "Take 1", "frames": "1-100",
            "chunk_size": 25, "output_dir": "/farm/relit", "relight_script": "{relight_batch}"}
    base.update(settings)
    out = subprocess.run(["node", str(harness), str(JOB_JS), json.dumps(base)], check=True,
                         capture_output=True, text=True, timeout=60)
    return json.loads(out.stdout)


def chunk_frames(task):
    args = task["commands"][0]["params"]["args"]
    first, last = map(int, re.fullmatch(r"(-?\d+)-(-?\d+)", args[args.index("--frames") + 1]).groups())
    return list(range(first, last + 1))


@pytest.mark.parametrize("frames,chunk,start,end", [
    ("1-100", 25, 1, 100), ("7-30", 5, 7, 30), ("-3-4", 3, -3, 4), ("12", 10, 12, 12),
    ("1-250", 1000, 1, 250), ("5-9", 1, 5, 9), (" 2 - 11 ", 4, 2, 11)])
def test_chunks_cover_the_range_exactly_once(tmp_path, frames, chunk, start, end):
    result = compile_job(tmp_path, frames=frames, chunk_size=chunk)
    assert "error" not in result
    covered = [f for t in result["tasks"] for f in chunk_frames(t)]
    expected = list(range(start, end + 1))
    assert sorted(covered) == expected          # every frame ...
    assert len(covered) == len(set(covered))    # ... exactly once
    assert all(len(chunk_frames(t)) <= chunk for t in result["tasks"])


def test_task_runs_the_batch_script_on_the_blend_file(tmp_path):
    result = compile_job(tmp_path, frames="1-10", chunk_size=10, hdri="/hdri/studio.exr",
                         preset="fast", write_matte=True)
    (task,) = result["tasks"]
    assert task["type"] == "blender" and task["name"] == "relight-1-10"
    cmd = task["commands"][0]
    assert cmd["type"] == "blender-render" and cmd["totalFrames"] == 10
    params = cmd["params"]
    assert params["blendfile"] == "/farm/shot.blend"
    assert params["args"] == ["--python", "{relight_batch}", "--", "--strip", "Take 1",
                              "--out", "/farm/relit", "--hdri", "/hdri/studio.exr",
                              "--preset", "fast", "--matte", "--frames", "1-10"]


def test_scene_lights_flag_and_defaults(tmp_path):
    result = compile_job(tmp_path, frames="3-4", scene_lights=True)
    args = result["tasks"][0]["commands"][0]["params"]["args"]
    assert "--scene-lights" in args and "--hdri" not in args and "--preset" not in args
    keys = {s["key"] for s in result["jobType"]["settings"]}
    assert {"blendfile", "strip", "frames", "chunk_size", "output_dir"} <= keys


@pytest.mark.parametrize("frames", ["10-1", "1-", "a-b", ""])
def test_bad_frame_ranges_are_refused(tmp_path, frames):
    result = compile_job(tmp_path, frames=frames)
    assert result["tasks"] == []
    assert "frames" in result["error"]
