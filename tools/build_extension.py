"""Build installable extension zips, one per platform, with the runtime wheels bundled.

    .venv/bin/python tools/build_extension.py [--platform linux-x64 ...] [--offline]

Downloads the onnxruntime, OpenEXR, PyAV, OpenColorIO and threadpoolctl wheels pinned in
requirements.txt for each platform (never numpy: Blender ships its own) into build/wheels/,
stages only the extension's files in build/stage/ with a generated manifest listing the wheels,
validates it with the extension tool shipped in the bpy wheel, and builds
dist/portrait_relight-<version>-<platform>.zip.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import re
import shutil
import subprocess
import sys
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]
# runtime imports beyond Blender's own numpy
BUNDLED = ("onnxruntime", "OpenEXR", "av", "opencolorio", "threadpoolctl")
# Blender platform name -> pip platform tags (pip also accepts older tags of the same family).
PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_14_0_arm64", "macosx_11_0_arm64"],
}
PYTHON_VERSION = "3.11"  # Blender 4.2 to 5.0 embed Python 3.11
# What the extension is made of; everything else (training/, tests/, bench/, .venv) stays out.
INCLUDE_DIRS = ("addon", "ops", "ui", "models")
INCLUDE_FILES = ("__init__.py", "scripts/relight_batch.py")
INCLUDE_SUFFIXES = {".py", ".json", ".onnx", ".npz", ".md", ".txt"}
NOTICE_GLOBS = ("LICENSE*", "COPYING*", "NOTICE*")


class BuildError(Exception):
    pass


def pinned_versions(requirements: pathlib.Path) -> dict[str, str]:
    pins = {}
    for line in requirements.read_text().splitlines():
        m = re.match(r"^\s*([A-Za-z0-9_.-]+)\s*==\s*([^\s#;]+)", line)
        if m:
            pins[m.group(1).lower()] = m.group(2)
    missing = [p for p in BUNDLED if p.lower() not in pins]
    if missing:
        raise BuildError(f"requirements.txt pins no version for {', '.join(missing)}")
    return {p: pins[p.lower()] for p in BUNDLED}


def blender_ext_tool() -> pathlib.Path:
    """The extension command-line tool inside the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError("the bpy module is not installed; run `bash tools/bootstrap.sh` first")
    found = sorted(pathlib.Path(spec.submodule_search_locations[0]).glob(
        "*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise BuildError("the bpy wheel holds no bl_pkg/cli/blender_ext.py")
    return found[-1]


def download_wheels(platform: str, pins: dict[str, str], wheel_dir: pathlib.Path,
                    offline: bool) -> list[pathlib.Path]:
    """The platform's wheels, downloaded once into wheel_dir/<platform> and reused after."""
    target = wheel_dir / platform
    target.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:",
           "--no-deps", "--python-version", PYTHON_VERSION, "--dest", str(target)]
    for tag in PLATFORMS[platform]:
        cmd += ["--platform", tag]
    if offline:
        cmd += ["--no-index", "--find-links", str(target)]
    cmd += [f"{name}=={version}" for name, version in pins.items()]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise BuildError(f"pip could not download the {platform} wheels:\n{done.stderr.strip()}")
    wheels = []
    for name, version in pins.items():
        stem = re.sub(r"[-_.]+", "_", name).lower()
        hits = [w for w in target.glob("*.whl")
                if w.name.lower().startswith(f"{stem}-{version}-")]
        if len(hits) != 1:
            raise BuildError(f"expected one {name} {version} wheel for {platform} in {target}, "
                             f"found {len(hits)}")
        wheels.append(hits[0])
    return wheels


def stage_sources(stage: pathlib.Path) -> None:
    for folder in INCLUDE_DIRS:
        for path in sorted((ROOT / folder).rglob("*")):
            if (path.is_file() and path.suffix in INCLUDE_SUFFIXES
                    and "__pycache__" not in path.parts
                    and not path.is_relative_to(ROOT / "models" / "research")):
                # models/research: ablation and frontier variants, measured, never offered
                _copy(path, stage)
    for name in INCLUDE_FILES:
        _copy(ROOT / name, stage)
    for pattern in NOTICE_GLOBS:
        for path in ROOT.glob(pattern):
            _copy(path, stage)


def _copy(path: pathlib.Path, stage: pathlib.Path) -> None:
    if not path.is_file():
        raise BuildError(f"{path.relative_to(ROOT)} is missing from the checkout")
    dest = stage / path.relative_to(ROOT)
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(path, dest)


def write_manifest(stage: pathlib.Path, platforms: list[str], wheels: list[str]) -> dict:
    """The source manifest with the platforms and wheels filled in; returns it parsed."""
    text = (ROOT / "blender_manifest.toml").read_text()
    listed = ",\n".join(f'  "./wheels/{w}"' for w in wheels)
    plats = ", ".join(f'"{p}"' for p in platforms)
    text, n = re.subn(r"(?m)^wheels\s*=\s*\[\s*\]\s*$",
                      f"platforms = [{plats}]\nwheels = [\n{listed},\n]", text)
    if n != 1:
        raise BuildError("blender_manifest.toml must hold exactly one `wheels = []` line")
    # The staged tree holds only shipped files, so the developer tree's exclusions are moot.
    text = re.sub(r"(?ms)^\[build\].*", "", text)
    (stage / "blender_manifest.toml").write_text(text)
    return tomllib.loads(text)


def run_tool(tool: pathlib.Path, *args: str) -> str:
    done = subprocess.run([sys.executable, str(tool), *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise BuildError(f"blender_ext {args[0]} failed:\n{done.stdout}{done.stderr}".strip())
    return done.stdout


def build(platforms: list[str], out_dir: pathlib.Path, wheel_dir: pathlib.Path,
          offline: bool = False, stage: pathlib.Path | None = None) -> list[pathlib.Path]:
    pins = pinned_versions(ROOT / "requirements.txt")
    tool = blender_ext_tool()
    stage = stage or ROOT / "build" / "stage"
    shutil.rmtree(stage, ignore_errors=True)
    (stage / "wheels").mkdir(parents=True)
    names = []
    for platform in platforms:
        for wheel in download_wheels(platform, pins, wheel_dir, offline):
            shutil.copy2(wheel, stage / "wheels" / wheel.name)
            names.append(wheel.name)
    stage_sources(stage)
    manifest = write_manifest(stage, platforms, sorted(set(names)))
    run_tool(tool, "validate", str(stage))
    out_dir.mkdir(parents=True, exist_ok=True)
    run_tool(tool, "build", "--source-dir", str(stage), "--output-dir", str(out_dir),
             "--split-platforms")
    zips = [out_dir / f"{manifest['id']}-{manifest['version']}-{p.replace('-', '_')}.zip"
            for p in platforms]
    missing = [z.name for z in zips if not z.is_file()]
    if missing:
        raise BuildError(f"the build did not produce {', '.join(missing)}")
    return zips


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", action="append", choices=sorted(PLATFORMS),
                        help="build only this platform (repeatable); default: all")
    parser.add_argument("--out", type=pathlib.Path, default=ROOT / "dist")
    parser.add_argument("--wheels", type=pathlib.Path, default=ROOT / "build" / "wheels",
                        help="wheel cache folder (one sub-folder per platform)")
    parser.add_argument("--offline", action="store_true",
                        help="use only wheels already in the cache; never touch the network")
    args = parser.parse_args(argv)
    try:
        zips = build(args.platform or list(PLATFORMS), args.out, args.wheels, args.offline)
    except BuildError as err:
        print(f"build_extension: {err}", file=sys.stderr)
        return 1
    for z in zips:
        print(f"built {z} ({z.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
