"""The package's layout: size limits, imports that point down, no cycles, DVC deps complete.

Everything here reads the source with ``ast``; nothing is imported or run.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src"
PKG = SRC / "generalist_control"

MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60

#: Layers from the bottom up: a module may import only from its own layer or lower ones.
LAYERS = [
    {"common"},
    {"dynamics", "plants"},
    {"simulation"},
    {"data"},
    {"model"},
    {"deploy"},
    {"tracking"},
    {"training", "evaluation", "adaptation"},
    {"reports", "sweeps"},
    # entry points
    {
        "generate",
        "generate_families",
        "train",
        "evaluate",
        "report",
        "tune",
        "sweep",
        "adapt",
        "unseen",
    },
]
#: Sibling packages of one layer that must not import each other.
SEPARATE = [{"training", "evaluation"}, {"adaptation", "evaluation"}, {"reports", "sweeps"}]
#: Heavy, optional dependencies that may be imported inside a function (matplotlib: only
#: where figures are drawn; mlflow: a second of imports that a command which logs nothing
#: does not pay; onnxruntime: only for the ONNX backend).
LAZY_OK = {
    "mlflow", "mlflow.entities", "mlflow.exceptions", "mlflow.tracking", "onnxruntime",
    "matplotlib", "matplotlib.pyplot",
}  # fmt: skip


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = path.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _top(name: str) -> str:
    """The stage a module belongs to: ``generalist_control.<top>...``."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else ""


def _layer(name: str) -> int:
    top = _top(name)
    for i, group in enumerate(LAYERS):
        if top in group:
            return i
    return -1  # the package root (__init__)


def _imports(tree: ast.Module) -> list[tuple[str, bool, int]]:
    """``(module, at top level, line)`` of every project import in the tree."""
    found = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            if isinstance(child, ast.ImportFrom) and child.module:
                names = [child.module]
                if child.module == "generalist_control":
                    names = [f"generalist_control.{a.name}" for a in child.names]
                for n in names:
                    found.append((n, not in_function, child.lineno))
            elif isinstance(child, ast.Import):
                for a in child.names:
                    found.append((a.name, not in_function, child.lineno))
            visit(child, nested)

    visit(tree, False)
    return found


def _project(name: str) -> str | None:
    """The project module an import names (a module, or the module holding a name)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name if name.startswith("generalist_control") else None


TREES = {name: ast.parse(path.read_text()) for name, path in MODULES.items()}
GRAPH = {
    name: {
        m
        for imp, top, _ in _imports(tree)
        if top and (m := _project(imp)) is not None and m != name
    }
    for name, tree in TREES.items()
}


def test_no_module_is_over_400_lines():
    long = {
        n: len(p.read_text().splitlines())
        for n, p in MODULES.items()
        if len(p.read_text().splitlines()) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_is_over_60_lines():
    long = {}
    for name, tree in TREES.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                start = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                size = node.end_lineno - start + 1
                if size > MAX_FUNCTION_LINES:
                    long[f"{name}.{node.name}"] = size
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (docstring included): {long}"


def test_no_project_import_inside_a_function():
    """Except an entry point's work (``train.run``'s Lightning): loaded once the config is
    read, so that ``--help`` and a refused config answer without its seconds of imports."""
    inside = [
        f"{name}:{line} imports {imp}"
        for name, tree in TREES.items()
        for imp, top, line in _imports(tree)
        if not top
        and (imp.startswith("generalist_control") or imp not in LAZY_OK)
        and not (name.split(".")[-1] in LAYERS[-1] and imp.startswith("generalist_control."))
    ]
    allowed = ", ".join(sorted(LAZY_OK))
    assert not inside, f"imports inside functions (only {allowed} may be): {inside}"


def test_no_function_below_the_entry_points_takes_a_dictconfig():
    """Issue 49: entry points read the config once into typed settings or plain mappings.

    Exempt: the entry points' decorator (``common.stage_main``) and the methods of Hydra
    callbacks, whose interface Hydra defines (``on_run_start(config: DictConfig)``).
    """
    entry = LAYERS[-1]
    taking = []
    for name, tree in TREES.items():
        if name.split(".")[-1] in entry or name.endswith("common.stage_main"):
            continue
        hydra_hooks = {
            id(f)
            for c in ast.walk(tree)
            if isinstance(c, ast.ClassDef) and any("Callback" in ast.unparse(b) for b in c.bases)
            for f in c.body
        }
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
                and id(node) not in hydra_hooks
            ):
                args = [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]
                if any(a.annotation and "DictConfig" in ast.unparse(a.annotation) for a in args):
                    taking.append(f"{name}.{node.name}")
    assert not taking, f"functions below the entry points that take a DictConfig: {taking}"


def test_imports_point_down_the_layers():
    up = []
    for name, deps in GRAPH.items():
        for dep in deps:
            if _layer(dep) > _layer(name):
                up.append(f"{name} -> {dep}")
            for group in SEPARATE:
                a, b = _top(name), _top(dep)
                if a != b and {a, b} <= group:
                    up.append(f"{name} -> {dep} (siblings)")
    assert not up, "imports that point up or sideways: " + "; ".join(sorted(up))


def test_there_is_no_import_cycle():
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, path: list[str]) -> bool:
        state[node] = 1
        for dep in sorted(GRAPH.get(node, ())):
            if state.get(dep) == 1:
                cycle.extend([*path[path.index(dep) :], dep] if dep in path else [node, dep])
                return True
            if state.get(dep) is None and visit(dep, [*path, dep]):
                return True
        state[node] = 2
        return False

    for name in sorted(GRAPH):
        if state.get(name) is None and visit(name, [name]):
            break
    assert not cycle, "import cycle: " + " -> ".join(cycle)


def _closure(start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        todo += GRAPH.get(n, ())
        # a package's __init__ runs when any of its modules is imported
        parent = n.rpartition(".")[0]
        if parent in MODULES:
            todo.append(parent)
    return seen


@pytest.mark.parametrize("stage", ["generate", "train", "evaluate"])
def test_dvc_stage_depends_on_all_the_code_it_imports(stage):
    spec = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"][stage]
    deps = [REPO / d for d in spec["deps"]]
    entry = spec["cmd"].split("-m ")[1].split()[0]
    missing = []
    for mod in sorted(_closure(entry)):
        path = MODULES[mod]
        if not any(path == d or d in path.parents for d in deps):
            missing.append(str(path.relative_to(REPO)))
    assert not missing, f"dvc.yaml stage {stage} does not depend on {missing}"
    # the stage's code dependencies exist
    code = [d for d in deps if SRC in d.parents]
    assert all(d.exists() for d in code), [str(d) for d in code if not d.exists()]


def test_readme_layout_table_matches_the_tree():
    rows = [
        line
        for line in (REPO / "README.md").read_text().splitlines()
        if line.startswith("| `src/generalist_control/")
    ]
    listed: set[str] = set()
    for row in rows:
        cell = row.split("|")[1]
        for item in cell.replace("`", "").split(","):
            item = item.strip()
            path = (
                PKG / item[len("src/generalist_control/") :] if item.startswith("src/") else None
            )
            if path is None:
                path = (PKG / item) if (PKG / item).exists() else None
            assert path.exists(), f"README lists {item!r}, which is not in the tree"
            listed.add(path.relative_to(PKG).as_posix().rstrip("/") if path != PKG else "")
    packages = {p.parent.relative_to(PKG).as_posix() for p in PKG.glob("*/__init__.py")}
    entries = {p.name for p in PKG.glob("*.py") if p.name != "__init__.py"}
    assert packages <= listed, f"sub-packages missing from README's layout: {packages - listed}"
    assert entries <= listed, f"entry modules missing: {entries - listed}"
    # every module named in the table's text exists in its sub-package
    for row in rows:
        pkg_cell = row.split("|")[1].strip().strip("`").split("`")[0].rstrip("/")
        pkg = PKG / pkg_cell[len("src/generalist_control/") :]
        if not (pkg / "__init__.py").exists():
            continue
        for name in re.findall(r"`(\w+)`", row.split("|")[2]):
            if (pkg / f"{name}.py").exists() or name in {"run", "main"}:
                continue
            assert any(p.stem == name for p in PKG.rglob("*.py")), f"{name} in README: no module"
