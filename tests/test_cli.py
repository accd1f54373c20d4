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
