"""The package's layering: every subpackage imports only the layers below it.

Read from the source (every ``import`` statement, at module level or inside functions), so
an upward import fails here whether or not any test happens to execute it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "spdslam"

#: What each layer may import (besides itself, ``spdslam._version`` and ``spdslam._cache``,
#: the base modules), lowest first.
ALLOWED = {
    "geometry": set(),
    "factors": {"geometry"},
    "solver": {"geometry", "factors"},
    "io": {"geometry", "factors", "solver"},
    "synthetic": {"geometry", "io"},
    "frontend": {"geometry", "io"},
    "mapping": {"geometry", "factors", "solver", "io", "frontend"},
    "evaluation": {"geometry", "io"},
    "experiments": {"geometry", "factors", "solver", "io", "synthetic", "mapping", "evaluation"},
    "cli": {"geometry", "factors", "solver", "io", "synthetic", "frontend", "mapping",
            "evaluation", "experiments"},
}


def _imported_layers(path: Path, layer: str) -> set[str]:
    """The spdslam subpackages a module imports."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's package
                parts = ["spdslam", layer][: 3 - node.level] if node.level <= 2 else []
                target = ".".join(parts + ([node.module] if node.module else []))
                names = [target] if node.module else [f"{target}.{a.name}" for a in node.names]
            else:
                names = [node.module or ""]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "spdslam" and len(parts) > 1 and parts[1] not in ("_version", "_cache"):
                out.add(parts[1])
    return out - {layer}


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_layer_imports_only_the_layers_below(layer):
    files = sorted((PKG / layer).glob("*.py"))
    assert files, f"no package spdslam/{layer}"
    for path in files:
        bad = _imported_layers(path, layer) - ALLOWED[layer]
        assert not bad, f"{path.relative_to(PKG.parent)} imports {sorted(bad)} (layer {layer!r})"


def test_the_layers_are_the_whole_package():
    packages = {p.name for p in PKG.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages == set(ALLOWED)
    flat = sorted(p.name for p in PKG.glob("*.py"))
    assert flat == ["__init__.py", "_cache.py", "_version.py"], f"modules outside the layers: {flat}"


def test_the_order_is_acyclic():
    """ALLOWED itself only points downwards (a topological order exists)."""
    order = list(ALLOWED)
    for i, layer in enumerate(order):
        assert ALLOWED[layer] <= set(order[:i]), layer


def test_the_resolver_sees_upward_imports(tmp_path):
    """The check can fail: relative and absolute upward imports, in functions too."""
    f = tmp_path / "m.py"
    f.write_text("from ..mapping import run_sequence\n"
                 "def g():\n    import spdslam.cli\n    from .. import evaluation\n"
                 "from . import _local\nfrom .._version import __version__\n")
    assert _imported_layers(f, "geometry") == {"mapping", "cli", "evaluation"}


def _module_imports(path: Path, layer: str) -> set[str]:
    """The sibling modules (same subpackage, ``__init__`` aside) a module imports, at module
    level or inside functions: ``from .x import …``, ``from . import x``, ``spdslam.layer.x``."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            out |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            parts = node.module.split(".")
            if parts[:2] == ["spdslam", layer] and len(parts) > 2:
                out.add(parts[2])
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[:2] == ["spdslam", layer] and len(parts) > 2:
                    out.add(parts[2])
    return out


def import_circles(folder: Path, layer: str) -> list[list[str]]:
    """The import circles among a subpackage's modules (strongly connected components of
    more than one module, or a module importing itself), each sorted."""
    mods = {p.stem: p for p in folder.glob("*.py") if p.stem != "__init__"}
    graph = {m: _module_imports(p, layer) & set(mods) for m, p in mods.items()}
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph[v]:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("layer", sorted(ALLOWED))
def test_no_import_circle_inside_a_subpackage(layer):
    assert import_circles(PKG / layer, layer) == []


def test_the_circle_check_finds_circles(tmp_path):
    """It can fail: a circle through a function-level import, and one of three modules."""
    (tmp_path / "_a.py").write_text("from ._b import f\n")
    (tmp_path / "_b.py").write_text("def f():\n    from . import _a\n")
    (tmp_path / "_c.py").write_text("import spdslam.pkg._d\n")
    (tmp_path / "_d.py").write_text("from ._e import g\n")
    (tmp_path / "_e.py").write_text("from spdslam.pkg._c import h\n")
    (tmp_path / "_f.py").write_text("from ._a import f\n")
    assert import_circles(tmp_path, "pkg") == [["_a", "_b"], ["_c", "_d", "_e"]]


def test_every_reader_is_reached_through_the_format_registry():
    """Outside ``spdslam/io``, no module calls a layout's reader or recogniser itself: they
    go through ``read_sequence`` / ``find_format``."""
    direct = {"import_fr3_cabinet", "import_oaslam", "import_rosbag", "read_canonical",
              "is_fr3_cabinet", "is_oaslam_layout", "is_rosbag"}
    for path in sorted(PKG.rglob("*.py")):
        if path.parent.name == "io":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                used = {a.name for a in node.names} & direct
                assert not used, f"{path.relative_to(PKG.parent)} imports {sorted(used)}"
