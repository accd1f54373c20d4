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
