"""Architecture rules from design.md that a test can enforce."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _imports(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0]


def _offenders(folder, forbidden):
    out = []
    for p in sorted((ROOT / folder).rglob("*.py")):
        bad = forbidden & set(_imports(p))
        if bad:
            out.append(f"{p.relative_to(ROOT)} imports {sorted(bad)}")
    return out


def test_addon_never_imports_blender_or_training():
    assert (ROOT / "addon").is_dir()
    assert _offenders("addon", {"bpy", "mathutils", "bmesh", "training", "torch"}) == []


def test_shipped_code_never_imports_training():
    assert _offenders("ops", {"training", "torch"}) == []
    assert _offenders("ui", {"training", "torch"}) == []
