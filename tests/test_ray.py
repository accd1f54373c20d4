"""Ray as the execution engine. The cases that start a local Ray instance live in
``tests/ray_cases.py`` and run here in a pytest process of their own (its docstring says
why); the two below start no Ray process."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import cli_invoke

#: Seconds one run of ``ray_cases.py`` may take (about 25 s here, on 2 cores).
CASES_TIMEOUT = 240.0

_SUMMARY = re.compile(r"\b(passed|failed|skipped|deselected|errors?)\b.* in [\d.]+s")


def _run_cases(markexpr: str) -> subprocess.CompletedProcess:
    cases = Path(__file__).with_name("ray_cases.py")
    # -n 0: no xdist workers in the child; -p no:cacheprovider: no .pytest_cache written by it
    args = [sys.executable, "-m", "pytest", str(cases), "-q", "-n", "0", "-p", "no:cacheprovider",
            "-m", markexpr, "--timeout", str(int(CASES_TIMEOUT))]
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=CASES_TIMEOUT,
                              cwd=cases.parent.parent, env=dict(os.environ), check=False)
    except subprocess.TimeoutExpired as e:
        out = (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        pytest.fail(f"tests/ray_cases.py did not finish in {CASES_TIMEOUT:g} s:\n{out[-4000:]}")


def _ended(r: subprocess.CompletedProcess) -> bool:
    """Whether pytest got as far as its summary line (a process ended from outside, by Ray or
    a signal, has none)."""
    lines = r.stdout.strip().splitlines()
    return bool(lines) and bool(_SUMMARY.search(lines[-1]))


@pytest.mark.timeout(2 * CASES_TIMEOUT + 60)
@pytest.mark.parametrize("markexpr", ["not slow", pytest.param("slow", marks=pytest.mark.slow)])
def test_the_ray_cases_pass_in_a_process_of_their_own(markexpr):
    """The cases of ``ray_cases.py`` that ``markexpr`` selects (the slow ones with ``-m
    slow``); a second run only when the first ended without pytest's summary (its process
    taken down), never after a failed assertion; the first run's output is shown if the
    second fails too, and printed if the second passes."""
    pytest.importorskip("ray")
    first = _run_cases(markexpr)
    runs = [first] if _ended(first) else [first, _run_cases(markexpr)]
    last = runs[-1]
    shown = "\n\n".join(f"--- run {k + 1} (exit {r.returncode}) ---\n{r.stdout[-6000:]}\n{r.stderr[-3000:]}"
                        for k, r in enumerate(runs))
    assert _ended(last) and last.returncode in (0, 5), shown  # 5: every case deselected
    if len(runs) == 2:
        print(f"tests/ray_cases.py: the first run ended without a summary (exit "
              f"{first.returncode}); the second passed:\n{first.stdout[-2000:]}\n{first.stderr[-2000:]}")


def test_an_address_where_nothing_answers_is_refused_at_once(tmp_path):
    pytest.importorskip("ray")
    r = cli_invoke("simulate", "--trials", "2", "--ray-address", "127.0.0.1:1", "--out", tmp_path / "s")
    assert r.exit_code == 2 and "nothing answers at 127.0.0.1:1" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = cli_invoke("simulate", "--trials", "2", "--ray-address", "nonsense", "--out", tmp_path / "s")
    assert r.exit_code == 2 and "expected auto, HOST:PORT or ray://HOST:PORT" in r.stderr


def test_without_ray_installed_the_option_says_how_to_install_it(monkeypatch, tmp_path):
    import builtins

    real = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray":
            raise ImportError("No module named 'ray'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    r = cli_invoke("simulate", "--trials", "2", "--ray", "--out", tmp_path / "s")
    assert r.exit_code == 2 and 'pip install -e ".[ray]"' in r.stderr
