"""Imports point down only (DESIGN.md "Layers"): a module may import from its own layer or below,
never above — not even inside a function. No allow-list.

    methods/core  <  scenes  <  references  <  methods/base.py, methods/studies.py
    <  methods/<m>/ (one paper each; never another method's package)  <  methods/registry.py
    <  reports  <  benchmarks, run_bench.py

Mitsuba/Dr.Jit are imported only from ``references`` and above (scenes and the core math stay
renderer-free), and ``reports`` modules form no import cycle among themselves.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("methods", "scenes", "references", "reports", "benchmarks")
RENDERER_MODULES = ("mitsuba", "drjit")


def layer(module: str) -> float | None:
    """Layer of a project module (None: not ours)."""
    p = module.split(".")
    if p[0] == "methods":
        if len(p) == 1 or p[1] in ("base", "studies"):
            return 3
        if p[1] == "core":
            return 0
        if p[1] == "registry":
            return 4.5
        return 4
    return {"scenes": 1, "references": 2, "reports": 5, "benchmarks": 6, "run_bench": 6}.get(p[0])


def method_package(module: str) -> str | None:
    p = module.split(".")
    return p[1] if layer(module) == 4 else None


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports(path: Path) -> list[tuple[str, int]]:
    """Every absolute import in the file, at any depth (functions, classes, try blocks)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.module, node.lineno))
            # `from methods import registry` imports methods.registry
            out += [(f"{node.module}.{a.name}", node.lineno) for a in node.names if layer(f"{node.module}.{a.name}") is not None
                    and node.module in ("methods", "methods.core", "reports", "scenes", "references")]
        elif isinstance(node, ast.ImportFrom) and node.level:
            raise AssertionError(f"{path}:{node.lineno}: relative import (use absolute imports)")
    return out


def project_files() -> list[Path]:
    files = [ROOT / "run_bench.py"]
    for pkg in PACKAGES:
        files += sorted((ROOT / pkg).rglob("*.py"))
    return files


def violations() -> list[str]:
    bad = []
    for f in project_files():
        me = module_name(f)
        L = layer(me)
        for target, line in imports(f):
            top = target.split(".")[0]
            where = f"{f.relative_to(ROOT)}:{line}: {me} imports {target}"
            if top in RENDERER_MODULES and L is not None and L < 2:
                bad.append(where + " (Mitsuba below references)")
            T = layer(target)
            if T is None or L is None:
                continue
            if T > L:
                bad.append(where + f" (layer {L} -> {T}: up)")
            elif T == L == 4 and method_package(target) != method_package(me):
                bad.append(where + " (across method packages)")
    return bad


def test_imports_point_down_only():
    bad = violations()
    assert not bad, "imports that go up a layer:\n" + "\n".join(bad)


def test_reports_have_no_import_cycle():
    graph: dict[str, set[str]] = {}
    for f in sorted((ROOT / "reports").glob("*.py")):
        me = module_name(f)
        graph[me] = {t for t, _ in imports(f) if t.startswith("reports.") and t != me}
    seen: dict[str, int] = {}  # 1 = on stack, 2 = done

    def visit(n: str, stack: list[str]) -> None:
        seen[n] = 1
        for m in sorted(graph.get(n, ())):
            if seen.get(m) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(m):] + [n, m]))
            if m not in seen:
                visit(m, stack + [n])
        seen[n] = 2

    for n in sorted(graph):
        if n not in seen:
            visit(n, [])


def test_checker_sees_imports_inside_functions(tmp_path):
    """The checker is not blind: an import of reports inside a function of a scenes-layer file is
    found (a planted file, parsed the same way)."""
    f = tmp_path / "planted.py"
    f.write_text("def f():\n    from reports.cells import Cell\n    import mitsuba\n")
    found = [t for t, _ in imports(f)]
    assert "reports.cells" in found and "mitsuba" in found
    assert layer("reports.cells") > layer("scenes.planted")
