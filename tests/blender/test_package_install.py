"""Build the Linux extension zip, install it into an isolated Blender user folder, enable it, and
relight a short clip through the installed copy (its batch script, its bundled wheels)."""

import importlib.util
import json
import pathlib
import subprocess
import sys
import zipfile

import bpy
import pytest

from conftest import ROOT, footage_scene

# Each runs in a fresh process whose Blender user folder is BLENDER_USER_RESOURCES.
INSTALL = r"""
import json, sys
import bpy

bpy.ops.extensions.package_install_files(filepath=sys.argv[1], repo="user_default",
                                         enable_on_install=True)
bpy.ops.wm.save_userpref()
print("RESULT " + json.dumps({
    "enabled": [k for k in bpy.context.preferences.addons.keys() if "relight" in k],
    "operator_module": bpy.types.RELIGHT_OT_relight_strip.__module__,
    "installed": sys.modules["bl_ext.user_default.portrait_relight"].__file__,
    # `blender -c relight` exists once the extension is enabled (its registration handle).
    "cli_command": sys.modules["bl_ext.user_default.portrait_relight.ops.batch"]._cli_handle
                   is not None,
}))
"""

# The installed copy's own batch script, as `python relight_batch.py ...` would run it; run
# in-process (runpy) only so that the modules it used can be listed afterwards.
RELIGHT = r"""
import json, runpy, sys
import bpy

script, args = sys.argv[1], sys.argv[2:]
sys.argv = [script, *args]
try:
    runpy.run_path(script, run_name="__main__")
    code = 0
except SystemExit as stop:
    code = stop.code
import onnxruntime, OpenEXR, av, PyOpenColorIO
print("RESULT " + json.dumps({
    "code": code,
    "operator_module": bpy.types.RELIGHT_OT_relight_strip.__module__,
    "modules": {m.__name__: m.__file__ for m in (onnxruntime, OpenEXR, av, PyOpenColorIO)},
    "strips": [s.name for s in bpy.context.scene.sequence_editor.strips],
}))
"""


def run_driver(code, args, env):
    done = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, timeout=600, env=env)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
    assert lines, done.stdout[-2000:] + done.stderr[-2000:]
    return json.loads(lines[-1][len("RESULT "):]), done


@pytest.fixture(scope="module")
def linux_zip(tmp_path_factory):
    tool = ROOT / "tools" / "build_extension.py"
    out = tmp_path_factory.mktemp("dist")
    cache = ROOT / "build" / "wheels"
    spec = importlib.util.spec_from_file_location("build_extension", tool)
    build_extension = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build_extension)
    offline = ((cache / "linux-x64").is_dir() and
               len(list((cache / "linux-x64").glob("*.whl"))) >= len(build_extension.BUNDLED))
    done = subprocess.run([sys.executable, str(tool), "--platform", "linux-x64",
                           "--out", str(out), *(["--offline"] if offline else [])],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    if done.returncode != 0 and "could not download" in done.stderr:
        pytest.skip(f"the platform wheels cannot be downloaded here: {done.stderr[-300:]}")
    assert done.returncode == 0, done.stderr
    (zip_path,) = out.glob("*.zip")
    return zip_path


def test_zip_holds_only_the_extension(linux_zip):
    names = zipfile.ZipFile(linux_zip).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops <= {"blender_manifest.toml", "__init__.py", "addon", "ops", "ui", "models",
                    "scripts", "wheels", "LICENSE", "NOTICE"} | {n for n in tops if
                                                                 n.startswith("LICENSE")}
    assert [n for n in names if n.startswith("scripts/")] == ["scripts/relight_batch.py"]
    wheels = sorted(n.split("/")[1].split("-")[0].lower() for n in names
                    if n.startswith("wheels/"))
    # never numpy: Blender has it
    assert wheels == ["av", "onnxruntime", "opencolorio", "openexr", "threadpoolctl"]
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    assert not [n for n in names if n.startswith("models/research/")]  # measured, not offered
    # the Portrait preset's face template, with its card and the heads' licence notice
    assert {"models/face-template/template.npz", "models/face-template/template.json"} <= set(names)
    manifest = zipfile.ZipFile(linux_zip).read("blender_manifest.toml").decode()
    assert 'platforms = ["linux-x64"]' in manifest


def test_installed_copy_relights_a_clip(extension, linux_zip, toy_models, tmp_path):
    strip = footage_scene(tmp_path, count=4)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    user = tmp_path / "blender_user"
    env = {"BLENDER_USER_RESOURCES": str(user), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}

    installed, _ = run_driver(INSTALL, [linux_zip], env)
    assert installed["enabled"] == ["bl_ext.user_default.portrait_relight"]
    assert installed["operator_module"].startswith("bl_ext.user_default.portrait_relight.")
    assert installed["cli_command"]
    ext_dir = pathlib.Path(installed["installed"]).parent
    assert ext_dir.is_relative_to(user)

    script = ext_dir / "scripts" / "relight_batch.py"
    result, done = run_driver(RELIGHT, [script, blend, "--strip", strip.name, "--models",
                                        toy_models, "--out", tmp_path / "out"], env)
    assert result["code"] == 0, done.stdout[-2000:] + done.stderr[-2000:]
    # The enabled extension ran, on the wheels bundled in the zip (not this venv's packages).
    assert result["operator_module"].startswith("bl_ext.user_default.portrait_relight.")
    for name, path in result["modules"].items():
        assert pathlib.Path(path).is_relative_to(user), (name, path)
    assert strip.name + " relit v001" in result["strips"]
    relit = sorted((tmp_path / "out" / strip.name / "v001" / "relit").glob("relit_*.exr"))
    assert len(relit) == 4
