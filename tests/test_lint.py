"""The package passes its linter and its type checker: ``python3 -m ruff check spdslam`` and
``python3 -m mypy spdslam`` with the configuration in pyproject.toml ([tool.ruff],
[tool.mypy]), so that the README's test command covers them (CI runs it)."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(tool: str, *args: str) -> None:
    if importlib.util.find_spec(tool) is None:
        pytest.skip(f"{tool} is not installed (it is in the test extra: pip install -e '.[test]')")
    p = subprocess.run([sys.executable, "-m", tool, *args], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    if p.returncode != 0:
        pytest.fail(f"python3 -m {tool} {' '.join(args)} failed (exit {p.returncode}):\n"
                    f"{p.stdout}{p.stderr}", pytrace=False)


def test_ruff_check():
    _run("ruff", "check", "--output-format", "concise", "spdslam")


def test_mypy():
    _run("mypy", "spdslam")
