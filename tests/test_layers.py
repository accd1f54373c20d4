"""The package's layering: every subpackage imports only the layers below it.

Read from the source (every ``import`` statement, at module level or inside functions), so
an upward import fails here whether or not any test happens to execute it.
"""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "spdslam"

#: What each layer may import (besides itself and ``spdslam._version``, the one base module),
#: lowest first.
ALLOWED = {
    "geometry": set(),
    "factors": {"geometry"},
    "solver": {"geometry", "factors"},
    "io": {"geometry", "factors", "solver"},
    "synthetic": {"geometry", "io"},
    "frontend": {"geometry", "factors", "solver", "io"},  # solver: its stored programs (stored_jit); factors:
    # the box's closed form
    "mapping": {"geometry", "factors", "solver", "io", "frontend"},
    "evaluation": {"geometry", "io"},
    "experiments": {"geometry", "factors", "solver", "io", "synthetic", "mapping", "evaluation"},
    "cli": {"geometry", "factors", "solver", "io", "synthetic", "frontend", "mapping",
            "evaluation", "experiments"},
}


def _resolve(node: ast.ImportFrom, package: list[str]) -> list[str]:
    """The absolute module path (its parts) of ``from … import``, a relative one resolved
    against ``package``, the importing module's package (``["spdslam", "io"]`` for
    ``spdslam/io/_readers.py`` and ``spdslam/io/__init__.py``)."""
    if not node.level:
        return (node.module or "").split(".")
    if node.level - 1 > len(package):
        return []
    base = package[: len(package) - (node.level - 1)]
    return base + (node.module.split(".") if node.module else [])


def _imported_layers(path: Path, layer: str) -> set[str]:
    """The spdslam subpackages a module imports."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            target = ".".join(_resolve(node, ["spdslam", layer]))
            names = [target] if node.module else [f"{target}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] == "spdslam" and len(parts) > 1 and parts[1] != "_version":
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
    assert flat == ["__init__.py", "_version.py"], f"modules outside the layers: {flat}"


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


# --- "_" means private ----------------------------------------------------------------------
# A module imports another package's names from that package (``from ..solver import
# Problem``), never from its ``_`` modules (``spdslam._version`` aside); and no ``_`` name
# (dunders aside) is imported from another module, inside one package too. Importing a private
# module of one's own package for its public names (``from ._parse import read_tum``) is fine.


def _is_dunder(name: str) -> bool:
    return name.startswith("__") and name.endswith("__")


def _is_module(parts: list[str], pkg: Path) -> bool:
    """Whether ``spdslam.a.b`` (``parts``) is a module or package of the tree at ``pkg``."""
    if not parts or parts[0] != "spdslam":
        return False
    where = pkg.joinpath(*parts[1:])
    return where.with_suffix(".py").is_file() or (where / "__init__.py").is_file()


def _package_of(path: Path, pkg: Path) -> list[str]:
    """The package a module of the tree at ``pkg`` belongs to (its folder), as parts."""
    return ["spdslam", *path.parent.relative_to(pkg).parts]


def _imports(path: Path, pkg: Path):
    """(line, absolute module parts, imported names or None) of every ``import`` statement of
    a module, at module level or inside functions; ``import a.b`` gives names None."""
    package = _package_of(path, pkg)
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            yield node.lineno, _resolve(node, package), [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name.split("."), None


def private_module_imports(path: Path, pkg: Path = PKG) -> list[str]:
    """``file:line module`` for each import of a private (``_``) module of another package
    than the module's own (``from ..solver._problem import Problem``, ``import
    spdslam.io._parse``, ``from ..io import _parse``); ``spdslam._version`` is allowed."""
    package, where = _package_of(path, pkg), path.relative_to(pkg.parent).as_posix()
    out = []
    for line, parts, names in _imports(path, pkg):
        if parts[:1] != ["spdslam"]:
            continue
        modules = [parts] + [parts + [n] for n in names or () if _is_module(parts + [n], pkg)]
        for mod in modules:
            private = [i for i, p in enumerate(mod) if i and p.startswith("_") and not _is_dunder(p)
                       and mod[:i + 1] != ["spdslam", "_version"]]
            if private and mod[: private[0]] != package:
                out.append(f"{where}:{line} {'.'.join(mod[: private[0] + 1])}")
    return out


def private_name_imports(path: Path, pkg: Path = PKG) -> list[str]:
    """``file:line name (from module)`` for each ``_`` name (not a dunder, not a module)
    imported from a spdslam module: ``from ._parse import _line``."""
    where = path.relative_to(pkg.parent).as_posix()
    out = []
    for line, parts, names in _imports(path, pkg):
        if parts[:1] != ["spdslam"]:
            continue
        for n in names or ():
            if n.startswith("_") and not _is_dunder(n) and not _is_module(parts + [n], pkg):
                out.append(f"{where}:{line} {n} (from {'.'.join(parts)})")
    return out


def _every_module(pkg: Path = PKG) -> list[Path]:
    return sorted(pkg.rglob("*.py"))


def test_no_module_imports_another_packages_private_module():
    bad = [b for path in _every_module() for b in private_module_imports(path)]
    assert not bad, "private modules of another package imported (import the package):\n" + "\n".join(bad)


def test_no_private_name_is_imported():
    bad = [b for path in _every_module() for b in private_name_imports(path)]
    assert not bad, "private names imported from another module (make them public):\n" + "\n".join(bad)


def test_the_privacy_checks_can_fail(tmp_path):
    """Both checks find what they forbid (relative, absolute, in functions, modules imported
    by ``from … import``), and pass what is allowed."""
    pkg = tmp_path / "spdslam"
    for f in ["__init__.py", "_version.py", "_cache.py", "solver/__init__.py", "solver/_compile.py",
              "io/__init__.py", "io/_parse.py", "cli/__init__.py", "cli/_other.py"]:
        (pkg / f).parent.mkdir(parents=True, exist_ok=True)
        (pkg / f).write_text("")
    (pkg / "cli" / "_app.py").write_text(
        "from .._cache import cache_dir\n"
        "from .._version import __version__\n"
        "from ..solver._compile import clear_caches\n"
        "from ..solver import Problem\n"
        "from . import _other\n"
        "from ._other import thing\n"
        "def f():\n"
        "    import spdslam.io._parse\n"
        "    from spdslam.io import _parse\n"
        "    import numpy._core\n")
    (pkg / "io" / "_readers.py").write_text(
        "from ._parse import _line, parse_line, __doc__\n"
        "from . import _parse\n"
        "from dataclasses import replace as _replace\n"
        "def g():\n"
        "    from spdslam.io._parse import _kind\n"
        "    from numpy import _pytesttester\n")
    (pkg / "__init__.py").write_text("from ._version import __version__\nfrom ._cache import cache_dir\n")
    app, readers = pkg / "cli" / "_app.py", pkg / "io" / "_readers.py"
    assert private_module_imports(app, pkg) == [
        "spdslam/cli/_app.py:1 spdslam._cache",
        "spdslam/cli/_app.py:3 spdslam.solver._compile",
        "spdslam/cli/_app.py:8 spdslam.io._parse",
        "spdslam/cli/_app.py:9 spdslam.io._parse",
    ]
    assert private_name_imports(app, pkg) == []
    assert private_module_imports(readers, pkg) == []
    assert private_name_imports(readers, pkg) == [
        "spdslam/io/_readers.py:1 _line (from spdslam.io._parse)",
        "spdslam/io/_readers.py:5 _kind (from spdslam.io._parse)",
    ]
    assert private_module_imports(pkg / "__init__.py", pkg) == []  # its own private modules


# --- the mapping layer's shape ------------------------------------------------------------
# In ``mapping`` and ``frontend`` no object reads another's ``_`` state (``self._x`` and
# ``cls._x`` are its own; ``super()._x`` is a base class's private, overridden or called);
# ``spdslam.mapping`` exports a small API, each name of it in docs/core.md.
SHAPED = ("mapping", "frontend")
MAX_MAPPING_NAMES = 25


def private_attribute_reads(path: Path) -> list[str]:
    """``file:line .name on what`` for each use of another object's ``_`` attribute."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not _is_dunder(node.attr):
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            out.append(f"{path.name}:{node.lineno} .{node.attr} on {ast.unparse(node.value)}")
    return out


def in_shaped_layers(check) -> list[str]:
    """What ``check`` finds in every module of ``SHAPED``."""
    return [b for layer in SHAPED for path in sorted((PKG / layer).glob("*.py")) for b in check(path)]


def test_no_object_in_mapping_or_frontend_reads_another_objects_private_state():
    bad = in_shaped_layers(private_attribute_reads)
    assert not bad, "reads of another object's private state:\n" + "\n".join(bad)


def test_the_private_state_check_can_fail(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("class A(B):\n    def f(self, o):\n        self._a = o._b\n        super()._c()\n"
                 "        return cls._d, o.__len__\n")
    assert private_attribute_reads(f) == ["m.py:3 ._b on o", "m.py:4 ._c on super()"]


def public_names(module) -> list[str]:
    return sorted(n for n in vars(module) if not n.startswith("_") and not inspect.ismodule(getattr(module, n))
                  and n != "annotations")


def test_the_mapping_package_exports_a_small_documented_api():
    import spdslam.mapping

    names = public_names(spdslam.mapping)
    assert len(names) <= MAX_MAPPING_NAMES, f"{len(names)} names: {', '.join(names)}"
    core = (PKG.parent / "docs" / "core.md").read_text(encoding="utf-8")
    missing = [n for n in names if f"`{n}`" not in core and f"`mapping.{n}`" not in core]
    assert not missing, "public names docs/core.md does not name: " + ", ".join(missing)


MAX_FUNCTION_LINES, MAX_PARAMETERS = 80, 8


def oversized_functions(path: Path) -> list[str]:
    """``file:line name`` of each function over ``MAX_FUNCTION_LINES`` lines or
    ``MAX_PARAMETERS`` parameters (``self`` and ``cls`` aside, ``*args`` and ``**kw`` counted)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            params = [p.arg for p in a.posonlyargs + a.args + a.kwonlyargs if p.arg not in ("self", "cls")]
            params += ["*"] * (a.vararg is not None) + ["**"] * (a.kwarg is not None)
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES or len(params) > MAX_PARAMETERS:
                out.append(f"{path.name}:{node.lineno} {node.name}: {lines} lines, {len(params)} parameters")
    return out


def test_no_function_in_mapping_or_frontend_is_over_80_lines_or_8_parameters():
    bad = in_shaped_layers(oversized_functions)
    assert not bad, "functions to split:\n" + "\n".join(bad)


def test_the_size_check_can_fail(tmp_path):
    f = tmp_path / "m.py"
    body = "".join(f"    x{i} = {i}\n" for i in range(80))
    f.write_text(f"def long():\n{body}\ndef wide(self, a, b, c, d, e, f, g, *h, **i):\n    pass\n"
                 "def fine(self, a, b, c, d, e, f, g, h):\n    pass\n")
    assert oversized_functions(f) == ["m.py:1 long: 81 lines, 0 parameters", "m.py:83 wide: 2 lines, 9 parameters"]
