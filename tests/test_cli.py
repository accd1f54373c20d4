"""The ``spdslam`` command-line tool: version, info, console script, error helper."""

from __future__ import annotations

import shutil
import subprocess

import pytest
import typer
from conftest import cli_runner

import spdslam
from spdslam import cli

runner = cli_runner()


def test_version_flag():
    result = runner.invoke(cli.app, ["--version"])
    assert result.exit_code == 0, result.output
    assert result.output.strip() == spdslam.__version__


def test_info_reports_jax_and_float64():
    result = runner.invoke(cli.app, ["info"])
    assert result.exit_code == 0, result.output
    out = result.output.lower()
    assert "jax" in out
    assert "float64" in out
    assert "enabled" in out  # float64 is switched on by importing spdslam
    assert spdslam.__version__ in result.output
    assert "sparse solver" in out


def test_a_bad_allocator_setting_is_one_line_and_exit_2(monkeypatch):
    monkeypatch.setenv("SPDSLAM_ALLOCATOR", "huge")
    result = runner.invoke(cli.app, ["info"])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [
        "spdslam: error: SPDSLAM_ALLOCATOR must be 'retain' or 'system', got 'huge'"]


@pytest.mark.parametrize("cholmod,cvxopt,name", [(True, True, "cholmod: CHOLMOD (scikit-sparse"),
                                                 (False, True, "cvxopt: CHOLMOD bundled with cvxopt"),
                                                 (False, False, "scipy: SuperLU")])
def test_info_names_the_solver_the_optimiser_uses(monkeypatch, cholmod, cvxopt, name):
    from spdslam.solver import _linear

    monkeypatch.setattr(_linear, "HAVE_CHOLMOD", cholmod)
    monkeypatch.setattr(_linear, "HAVE_CVXOPT", cvxopt)
    assert cli._app.sparse_solver_name().startswith(name)
    result = runner.invoke(cli.app, ["info"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert name in result.output


def test_callback_sets_compilation_cache(tmp_path, monkeypatch):
    import jax

    target = tmp_path / "cache-here"
    monkeypatch.setenv(cli.CACHE_ENV, str(target))
    old = jax.config.jax_compilation_cache_dir
    try:
        result = runner.invoke(cli.app, ["info"])
        assert result.exit_code == 0, result.output
        assert target.is_dir()
        assert jax.config.jax_compilation_cache_dir == str(target)
    finally:
        jax.config.update("jax_compilation_cache_dir", old)


def test_cache_env_off_turns_the_cache_off(monkeypatch):
    import jax

    monkeypatch.setenv(cli.CACHE_ENV, "off")
    old = jax.config.jax_compilation_cache_dir
    assert cli.enable_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir == old
    result = runner.invoke(cli.app, ["info"])
    assert result.exit_code == 0, result.output
    assert "off" in result.output.split("compilation cache")[1].splitlines()[0]


def test_unusable_cache_dir_is_not_fatal(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert cli.enable_compilation_cache(blocker / "sub") is None


def test_fail_is_one_line_exit_2():
    probe = typer.Typer()

    @probe.command()
    def boom() -> None:
        cli.fail("bad input:\n  something is wrong")

    result = runner.invoke(probe, [])
    assert result.exit_code == 2
    assert result.output.strip() == "spdslam: error: bad input: something is wrong"


def test_console_script_on_path():
    exe = shutil.which("spdslam")
    assert exe is not None, "the 'spdslam' console script is not installed; run: bash install.sh"
    proc = subprocess.run(
        [exe, "--version"], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == spdslam.__version__


# --- imports that cost only what a command uses ----------------------------------------------

#: Packages that the help of the commands must not import (JAX alone takes ~1 s).
HEAVY = ("jax", "jaxlib", "scipy", "matplotlib", "rerun", "ray")

_HELP_PROBE = """
import sys
{prelude}
import typer
from typer.testing import CliRunner

from spdslam.cli import app

runner = CliRunner()
names = sorted(typer.main.get_command(app).commands)
for args in [["--help"]] + [[name, "--help"] for name in names]:
    result = runner.invoke(app, args, terminal_width=100)
    assert result.exit_code == 0 and "Usage" in result.output, (args, result.output)
print(" ".join(names))
print(" ".join(m for m in {heavy!r} if m in sys.modules))
"""


def _probe(code: str) -> list[str]:
    """The lines ``code`` prints, run in a fresh Python process."""
    import sys

    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()


def test_the_help_imports_neither_jax_nor_the_plotting_and_ray_packages():
    """``spdslam --help`` and every ``spdslam COMMAND --help`` are built from ``_help.FACTS``
    and the commands import what they use when they run: no JAX, SciPy, matplotlib, rerun or
    Ray in the process afterwards (the probe sees them when they are there)."""
    names, heavy = _probe(_HELP_PROBE.format(prelude="", heavy=HEAVY))
    assert {"run", "import", "demo", "simulate", "check", "info"} <= set(names.split())
    assert heavy == "", f"the help imported {heavy}"
    assert _probe(_HELP_PROBE.format(prelude="import jax", heavy=HEAVY))[1].split()[:2] == ["jax", "jaxlib"]


def test_the_help_facts_are_the_packages_facts():
    """``_help.FACTS`` (what the help shows of the methods, sigmas, robust kernels and groups,
    formats and settings) is what the packages say."""
    from spdslam.cli._help import FACTS, facts_source, live_facts

    live = live_facts()
    assert FACTS == live, ("spdslam/cli/_help.py's FACTS is stale; replace it by:\n" + facts_source(live))
    scope: dict = {"Any": object}
    exec(facts_source(live), scope)  # the source it prints is the same again
    assert scope["FACTS"] == live


def test_a_setting_the_help_copy_lacks_is_read_from_the_packages(monkeypatch):
    from spdslam.cli import _help

    assert _help.setting("online.window") == (30, "frames whose poses the fixed-lag problem keeps free")
    known = dict(_help.FACTS["settings"])
    known.pop("online.window")
    monkeypatch.setitem(_help.FACTS, "settings", known)
    monkeypatch.setattr(_help, "_MISSING", [])
    assert _help.setting("online.window") == (30, "frames whose poses the fixed-lag problem keeps free")
    assert _help.live_facts() != _help.FACTS  # and the copy's test asks for it to be renewed
    assert "online.window" in _help.live_facts()["settings"]
    with pytest.raises(KeyError, match="nonsense"):
        _help.setting("online.nonsense")


def test_the_compilation_cache_starts_with_a_command_not_with_its_help(tmp_path, monkeypatch):
    target = tmp_path / "cache-here"
    monkeypatch.setenv(cli.CACHE_ENV, str(target))
    result = runner.invoke(cli.app, ["run", "--help"])
    assert result.exit_code == 0, result.output
    assert not target.exists()


def test_importing_spdslam_is_lazy_and_float64_stays_on():
    """``import spdslam`` imports no subpackage (nor JAX); the core's names come on first use,
    and JAX computes in float64 whether it is imported before or after spdslam."""
    code = ("import sys\nimport spdslam\n"
            "print(sorted(m for m in sys.modules if m.startswith(('spdslam.', 'jax'))))\n"
            "from spdslam import InverseBoxFactor, X, se3\n"
            "import jax.numpy as jnp\n"
            "print(jnp.ones(1).dtype, InverseBoxFactor.__module__, spdslam.solver.X is X, se3.__name__)\n"
            "print(all(hasattr(spdslam, n) for n in dir(spdslam)), 'InverseBoxFactor' in dir(spdslam))\n")
    loaded, used, listed = _probe(code)
    assert loaded == "['spdslam._version']"
    assert used == "float64 spdslam.factors._box True spdslam.geometry.se3"
    assert listed == "True True"
    assert _probe("import jax\nimport spdslam\nimport jax.numpy as jnp\nprint(jnp.ones(1).dtype)") == ["float64"]
    with pytest.raises(AttributeError, match="has no attribute 'nonsense'"):
        spdslam.nonsense  # noqa: B018


def test_collector_paused_freezes_what_exists_and_restores_the_collector():
    """``start`` and ``run``'s reading: the collector off within the block, what exists at its
    end frozen, and the collector afterwards as it was (left off when it was off)."""
    import gc

    from spdslam.cli._app import collector_paused

    gc.unfreeze()
    try:
        with collector_paused():
            assert not gc.isenabled()
            kept = [[] for _ in range(10)]
        assert gc.isenabled() and gc.get_freeze_count() > len(kept)
        gc.unfreeze()
        gc.disable()
        with collector_paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()
        gc.unfreeze()
