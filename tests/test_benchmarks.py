"""Smoke runs of the performance scripts (``--quick``): they finish and write the JSON that
docs/performance.md reads its fields from. Slow (compiles several programs); run with
``python3 -m pytest -m slow tests/test_benchmarks.py``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.slow


def run(script: str, *args: str) -> str:
    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args],
                       capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout


def test_sphere2500_quick(tmp_path):
    pytest.importorskip("gtsam")
    out = run("sphere2500.py", "--out", str(tmp_path / "s.json"))
    d = json.loads((tmp_path / "s.json").read_text())
    assert d["gtsam"]["lambda_trials"] >= d["gtsam"]["iterations"] > 0
    assert d["spdslam"]["iterations"] == 5
    for k in ("ratio_per_iteration", "ratio_per_trial", "ratio_total"):
        assert d[k] > 0
    assert "per λ trial" in out
    assert d["gtsam_dogleg"] is None


def test_sphere2500_dogleg_against_both_gtsam_optimisers(tmp_path):
    pytest.importorskip("gtsam")
    out = run("sphere2500.py", "--optimizer", "dogleg", "--out", str(tmp_path / "s.json"))
    d = json.loads((tmp_path / "s.json").read_text())
    assert d["gtsam_dogleg"]["iterations"] == 5 and d["gtsam_dogleg"]["ratio_total"] > 0
    assert "gtsam's dogleg:" in out


def test_sphere2500_floor_quick():
    pytest.importorskip("gtsam")
    out = run("sphere2500_floor.py")
    assert "default, 1 BLAS:" in out and "forward (solver), chunk 16:" in out
    assert "floor: " in out and "× gtsam's" in out


def test_simulation_quick(tmp_path):
    run("simulation.py", "--optimize", "yes", "--out", str(tmp_path / "sim.json"))
    d = json.loads((tmp_path / "sim.json").read_text())
    assert d["optimize"] == "yes"
    for name in ("cold", "warm"):
        p = d["passes"][name]
        assert p["solves"] == 6 * 6 * 2 and p["problem_iterations"] > 0
        assert p["us_per_problem_iteration"] > 0


def test_scaling_quick(tmp_path):
    out = run("scaling.py", "--out", str(tmp_path / "sc.json"))
    d = json.loads((tmp_path / "sc.json").read_text())
    (r,) = d["sizes"]
    assert (r["frames"], r["objects"]) == (1000, 10)
    b = r["breakdown_ms"]
    assert r["iteration_ms"] == pytest.approx(sum(b.values()))
    assert set(b) == {"linearise", "assemble", "damp", "factorise", "backsolve", "retract"}
    assert (tmp_path / "sc.png").stat().st_size > 0
    assert "1000" in out


def test_reference_quick(tmp_path):
    out = run("reference.py", "--out", str(tmp_path / "r.json"))
    d = json.loads((tmp_path / "r.json").read_text())
    assert len(d["cells"]) == 2 * 2 * 3  # angles × models × params at H
    for c in d["cells"]:
        assert c["trials"] == 8 and 0 <= c["ours"] <= 1 and 0 <= c["reference"] <= 1
        assert c["max_initial_cost_mismatch"] < 1e-9
    assert "| range | noise | model | param | ours | TRF |" in out
