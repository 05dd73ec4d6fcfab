"""The code's shape: imports flow one way (kernels and trajectories ← core ← parts and scenes ← engine ← studies
← API and CLI; kernels import only Warp; a part never imports the run config), no import circles (imports inside
functions counted), no module over 500 lines and no host function over 60 (a kernel body over 100)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("flightsim", "kernels", "trajectories")
LAYERS = [("kernels", "trajectories"), ("flightsim.core",),
          ("flightsim.instrument", "flightsim.platforms", "flightsim.scenes", "flightsim.outputs", "flightsim.scoring"),
          ("flightsim.engine",), ("flightsim.studies", "flightsim.calibration"),
          ("flightsim.api", "flightsim.cli", "flightsim.__main__", "flightsim")]
MAX_MODULE_LINES, MAX_FUNCTION_LINES, MAX_KERNEL_FUNCTION_LINES = 500, 60, 100
KERNEL_IMPORTS = {"warp", "functools", "dataclasses", "typing", "math", "__future__"}


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Every module of ours that ``name`` imports, at the top or inside a function (TYPE_CHECKING blocks aside)."""
    tree = ast.parse(path.read_text())
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            for n in ast.walk(node)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip or not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        else:
            base = node.module or ""
            if node.level:
                parts = name.split(".")[: len(name.split(".")) - node.level + (path.name == "__init__.py")]
                base = ".".join(parts + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names]
        for target in targets:
            while target and target not in modules and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in modules and target != name and not target.startswith(name + "."):
                found.add(target)
    return found


def _layer(name: str) -> int:
    return max((len(p), i) for i, group in enumerate(LAYERS) for p in group if name == p or name.startswith(p + "."))[1]


MODULES = _modules()
GRAPH = {name: _imports(name, path, MODULES) for name, path in MODULES.items()}


def test_imports_flow_one_way():
    upward = sorted(f"{m} -> {t}" for m, targets in GRAPH.items() for t in targets if _layer(t) > _layer(m))
    assert upward == []


def test_no_import_circles():
    index, low, stack, on_stack, circles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in GRAPH:
        if v not in index:
            visit(v)
    assert circles == []


@pytest.mark.parametrize("package", ["kernels", "trajectories"])
def test_the_lowest_packages_import_nothing_of_the_host(package):
    for name, path in MODULES.items():
        if name.split(".")[0] == package:
            assert all(t.split(".")[0] == package for t in GRAPH[name]), (name, GRAPH[name])


def test_kernels_import_only_warp():
    for name, path in MODULES.items():
        if name.startswith("kernels"):
            tree = ast.parse(path.read_text())
            roots = {(n.module or "").split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
            roots |= {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
            assert roots <= KERNEL_IMPORTS | {"kernels"}, (name, roots - KERNEL_IMPORTS)


def test_no_part_or_scene_imports_the_run_config():
    parts = [m for m in MODULES if _layer(m) <= 2]
    assert [m for m in parts if any(t.startswith("flightsim.engine") for t in GRAPH[m])] == []


def test_modules_and_functions_are_short():
    long = []
    for name, path in MODULES.items():
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            long.append(f"module {name}: {len(text.splitlines())} lines")
        limit = MAX_KERNEL_FUNCTION_LINES if name.startswith("kernels") else MAX_FUNCTION_LINES
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > limit:
                    long.append(f"function {name}:{node.name}: {lines} lines")
    assert long == []


def test_the_check_sees_an_upward_import_and_a_circle():
    """The checks above fail where they should: on a made-up module graph."""
    saved = dict(GRAPH)
    try:
        GRAPH["flightsim.scenes.scene"] = GRAPH["flightsim.scenes.scene"] | {"flightsim.engine.config"}
        with pytest.raises(AssertionError):
            test_imports_flow_one_way()
        with pytest.raises(AssertionError):
            test_no_import_circles()
    finally:
        GRAPH.clear()
        GRAPH.update(saved)


def _kernels_without_lean_options(sources: dict[str, str]) -> list[str]:
    """Kernel modules and decorators of ``sources`` that would compile a backward (adjoint) kernel or a grid-stride
    loop: each kernels/ module sets both off for its kernels, and a module of its own (``module="unique"``) does not
    inherit its file's options, so it must say so itself."""
    found = []
    for name, text in sources.items():
        tree = ast.parse(text)
        options = [node for node in ast.walk(tree) if isinstance(node, ast.Call)
                   and ast.unparse(node.func) == "wp.set_module_options"]
        if not any(ast.unparse(call.args[0]) == LEAN_MODULE for call in options):
            found.append(f"{name}: module options")
        for node in ast.walk(tree):
            for deco in getattr(node, "decorator_list", []):
                if isinstance(deco, ast.Call) and ast.unparse(deco.func) == "wp.kernel":
                    given = {k.arg: ast.unparse(k.value) for k in deco.keywords}
                    if given.get("module") == "'unique'" and (given.get("enable_backward") != "False"
                                                              or given.get("grid_stride") != "False"):
                        found.append(f"{name}:{node.name}")
    return found


LEAN_MODULE = "{'enable_backward': False, 'default_grid_stride': False}"


def test_every_kernel_compiles_a_lean_forward_pass():
    """Nothing differentiates through the simulator: every kernel compiles its forward pass only (a backward pass
    more than doubled the points kernel's compile time), launched one thread per element without a grid-stride loop
    (the loop's registers were spilled in the trace kernels: 156 → 80 bytes stored per thread, ptxas for sm_90)."""
    sources = {name: path.read_text() for name, path in MODULES.items()
               if name.startswith("kernels") and name != "kernels"}
    assert _kernels_without_lean_options(sources) == []
    lean = 'import warp as wp\nwp.set_module_options({"enable_backward": False, "default_grid_stride": False})\n'
    made_up = lean + '@wp.kernel(module="unique", enable_backward=False)\ndef k():\n    pass\n'
    assert _kernels_without_lean_options({"made_up": made_up}) == ["made_up:k"]
    assert _kernels_without_lean_options({"bare": "import warp as wp\n"}) == ["bare: module options"]
