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


def _module_name(path: pathlib.Path, root: pathlib.Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(package: pathlib.Path) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports, anywhere in the file (imports inside
    functions too: a late import still ties two modules together). Relative imports are
    resolved; ``from pkg import name`` counts as importing pkg.name where that is a module."""
    root = package.parent
    modules = {_module_name(p, root): p for p in package.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                edges |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    stem = base[:len(base) - node.level + 1] + ([node.module] if node.module else [])
                    target = ".".join(stem)
                else:
                    target = node.module
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    edges.add(sub if sub in modules else target)
        graph[name] = {e for e in edges if e in modules and e != name}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every group of modules that import each other, directly or round a loop (Tarjan's
    strongly connected components of more than one module)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_in_training():
    graph = import_graph(ROOT / "training")
    assert "training.run.train" in graph and "training.eval.evaluate" in graph
    assert "training.model.units" in graph["training.eval.predictors"]  # a late import counts too
    assert import_cycles(graph) == []


def test_the_cycle_check_finds_a_cycle(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from .. import c\n")
    (pkg / "c.py").write_text("import pkg.a\n")
    (pkg / "d.py").write_text("from . import a\n")  # imports into the cycle, is not part of it
    graph = import_graph(pkg)
    assert graph["pkg.a"] == {"pkg.sub.b"} and graph["pkg.sub.b"] == {"pkg.c"}
    assert import_cycles(graph) == [["pkg.a", "pkg.c", "pkg.sub.b"]]


PROJECT = ("addon", "ops", "ui", "bench", "training")


def _private_uses(path: pathlib.Path) -> list[str]:
    """Where ``path`` reaches into another project module's private names: ``from m import _x``,
    or ``m._x`` with m a project module it imported."""
    tree = ast.parse(path.read_text(), filename=str(path))
    modules, out = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {a.asname or a.name.split(".")[0] for a in node.names
                        if a.name.split(".")[0] in PROJECT}
        elif isinstance(node, ast.ImportFrom) and (node.level or (
                node.module or "").split(".")[0] in PROJECT):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {a.name}")
                else:
                    modules.add(a.asname or a.name)  # a module or not: checked by use below
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in modules and node.attr.startswith("_")
                and not node.attr.startswith("__")):
            out.append(f"{path.relative_to(ROOT)}:{node.lineno} uses {node.value.id}.{node.attr}")
    return out


def test_no_module_reaches_into_another_modules_private_names():
    """Shared code is public: what one module uses of another has a public name."""
    offences = [o for folder in PROJECT for p in sorted((ROOT / folder).rglob("*.py"))
                for o in _private_uses(p)]
    assert offences == []
