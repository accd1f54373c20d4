"""The simulation study: a tiny grid in CI (files, schema, sane numbers); the full grid on demand."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from conftest import cli_runner

from spdslam.cli import app
from spdslam.experiments import CSV_COLUMNS, StudyConfig, run_study

REQUIRED = [
    "angle", "noise", "model", "param", "trial", "success", "iterations_to_tol",
    "final_cost", "iou", "orientation_error_deg", "seconds",
]  # fmt: skip


def _read_rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_tiny_study_via_cli(tmp_path, monkeypatch):
    monkeypatch.setenv("SPDSLAM_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "sim"
    res = cli_runner().invoke(
        app,
        ["simulate", "--trials", "4", "--angles", "120", "--noise", "L,M", "--models", "inv,semi",
         "--params", "S,O", "--max-iters", "60", "--out", str(out)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    for name in ("trials.csv", "table.md", "convergence.png", "summary.json"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not list(out.glob(".*.tmp"))
    rows = _read_rows(out / "trials.csv")
    assert list(rows[0].keys())[: len(REQUIRED)] == REQUIRED
    assert len(rows) == 4 * 2 * 2 * 2  # trials × noise × models × params
    for r in rows:
        iou = float(r["iou"])
        assert 0.0 <= iou <= 1.0 + 1e-9
        assert np.isfinite(float(r["final_cost"])) and float(r["seconds"]) > 0
        if r["success"] == "1":
            assert int(r["iterations_to_tol"]) <= int(r["iterations"])
    # Noise-free boxes, small initial noise: every method finds the truth.
    low = [r for r in rows if r["noise"] == "L"]
    assert all(r["success"] == "1" for r in low)
    assert min(float(r["iou"]) for r in low) > 0.99
    assert max(float(r["orientation_error_deg"]) for r in low) < 0.1
    summary = json.loads((out / "summary.json").read_text())
    assert {c["param"] for c in summary["cells"]} == {"S", "O"}
    for c in summary["cells"]:
        sr = c["success_rate"]
        assert sr["low"] <= sr["estimate"] <= sr["high"]
    table = (out / "table.md").read_text()
    assert "(paper 24+24)" in table and "| L |" in table
    assert "µs per problem-iteration" in res.output


def test_bad_options_exit_2(tmp_path):
    runner = cli_runner()
    for args in (["--params", "X"], ["--noise", "Q"], ["--angles", "abc"], ["--angles", "0"],
                 ["--optimize", "maybe"]):
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "x"), *args])
        assert res.exit_code == 2, (args, res.output)
    assert not (tmp_path / "x").exists()


def test_optimized_compilation_gives_the_same_study():
    """``optimize`` changes how XLA compiles the solver, not what it computes."""
    base = dict(trials=3, angles=(120.0,), noise=("L",), models=("inv",), params=("O", "S"),
                max_iters=40)
    rows = [run_study(StudyConfig(**base, optimize=o)).rows for o in (False, True)]
    assert len(rows[0]) == len(rows[1]) == 6
    for a, b in zip(*rows):
        assert a["final_cost"] == pytest.approx(b["final_cost"], rel=1e-6, abs=1e-9)
        assert a["iou"] == pytest.approx(b["iou"], abs=1e-6)


def test_success_rule_and_iterations_to_tol():
    """The rule compares with the cost at the truth, not with any method's own result."""
    cfg = StudyConfig(trials=3, angles=(120.0,), noise=("L",), models=("inv",), params=("O",), max_iters=40)
    result = run_study(cfg)
    for r in result.rows:
        assert r["final_cost"] <= (1 + cfg.success_rtol) * r["truth_cost"] + cfg.success_atol
        assert r["success"]
    h = result.histories[("inv", "O")]
    assert h.shape == (3, cfg.max_iters + 1) and np.allclose(h[:, 0], 1.0)
    assert np.all(np.diff(h, axis=1) <= 1e-12)  # accepted costs never increase


def _without_timing(text: str) -> str:
    return "\n".join(line for line in text.splitlines() if not line.startswith("Wall time"))


@pytest.mark.slow
def test_default_run_reproduces_the_committed_table(tmp_path, monkeypatch):
    """`spdslam simulate --out DIR` (the paper's grid, 864 solves) reproduces
    docs/simulation/table.md, timings aside."""
    from pathlib import Path

    monkeypatch.setenv("SPDSLAM_CACHE_DIR", str(tmp_path / "cache"))
    res = cli_runner().invoke(app, ["simulate", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    rows = _read_rows(tmp_path / "trials.csv")
    assert len(rows) == 864
    committed = Path(__file__).resolve().parents[1] / "docs" / "simulation" / "table.md"
    assert _without_timing((tmp_path / "table.md").read_text()) == _without_timing(committed.read_text())
    assert set(CSV_COLUMNS) >= set(REQUIRED)


def test_protocols_are_named_validated_and_shape_the_views():
    """The protocol's free choices: the focal length scales the boxes about the principal
    point (same scenes otherwise), the cone keeps every pair of viewing directions within the
    viewing range, the arc keeps every view's elevation within the spread, and bad values
    are refused."""
    from spdslam.synthetic import PROTOCOLS, Protocol, get_protocol, make_scenes

    assert {"paper", "v1"} <= set(PROTOCOLS) and get_protocol("v1") is PROTOCOLS["v1"]
    assert StudyConfig().protocol == PROTOCOLS["paper"]
    assert StudyConfig(protocol="v1", n_views=6).protocol.n_views == 6
    narrow, wide = (make_scenes(3, 20, "L", 60.0, protocol=Protocol(focal=f)) for f in (500.0, 2000.0))
    c0, c1 = np.array([320.0, 240.0, 320.0, 240.0]), np.array([1280.0, 960.0, 1280.0, 960.0])
    np.testing.assert_allclose(wide.boxes - c1, 4.0 * (narrow.boxes - c0), rtol=1e-9, atol=1e-6)
    for pattern, angle in (("cone", 60.0), ("arc", 120.0)):
        pr = Protocol(pattern=pattern, elevation_deg=10.0)
        sc = make_scenes(5, 30, "L", angle, protocol=pr)
        eyes = np.asarray(sc.poses.translation())
        d = eyes - np.asarray(sc.truth.center)[:, None]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        if pattern == "cone":
            cos = np.einsum("bvi,bwi->bvw", d, d)
            assert np.degrees(np.arccos(np.clip(cos.min(), -1, 1))) <= angle + 1e-6
        else:
            assert np.degrees(np.abs(np.arcsin(d[..., 2]))).max() <= 10.0 + 1e-6
            az = np.unwrap(np.arctan2(d[..., 1], d[..., 0]), axis=1)
            assert np.degrees(np.ptp(az, axis=1)).max() <= angle + 1e-6
    for bad in (dict(focal=0.0), dict(distance=(6.0, 4.0)), dict(pattern="fan"),
                dict(elevation_deg=90.0), dict(n_views=2), dict(aim_jitter=-1.0)):
        with pytest.raises(ValueError):
            Protocol(**bad)
    with pytest.raises(ValueError, match="unknown protocol"):
        StudyConfig(protocol="v2")


def test_simulate_protocol_options(tmp_path):
    """--protocol and its overrides reach the scenes and are written down; bad ones exit 2
    with one line naming the option."""
    runner = cli_runner()
    out = tmp_path / "sim"
    res = runner.invoke(app, ["simulate", "--trials", "2", "--angles", "120", "--noise", "L", "--models", "inv",
                              "--params", "O", "--protocol", "v1", "--focal", "800", "--pattern", "arc",
                              "--distance", "3-4", "--views", "6", "--out", str(out)])
    assert res.exit_code == 0, res.output
    pr = json.loads((out / "summary.json").read_text())["config"]["protocol"]
    assert pr == {"name": "custom", "focal": 800.0, "distance": [3.0, 4.0], "pattern": "arc",
                  "elevation_deg": 15.0, "n_views": 6, "aim_jitter": 0.05}
    assert "Protocol custom: f = 800 px, cameras 3–4 m" in (out / "table.md").read_text()
    for args, option in ((["--distance", "4"], "--distance"), (["--pattern", "fan"], "--pattern"),
                         (["--views", "2"], "--views"), (["--protocol", "v2"], "--protocol"),
                         (["--elevation", "95"], "--elevation"), (["--focal", "-1"], "--focal")):
        res = runner.invoke(app, ["simulate", "--out", str(tmp_path / "x"), *args])
        assert res.exit_code == 2, (args, res.output)
        lines = res.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"spdslam: error: {option}:"), res.stderr
    assert not (tmp_path / "x").exists()


def test_a_study_in_chunks_is_the_study_in_one_batch(monkeypatch):
    """``run_study(chunk=…)`` solves a few problems at a time (bounded memory) and gives the
    same columns, histories and trials.csv fields as one batch; histories are kept for the
    first ``HISTORY_TRIALS`` trials of each cell only."""
    from spdslam.experiments import _study

    cfg = StudyConfig(trials=5, angles=(60.0, 120.0), noise=("M",), models=("inv",),
                      params=("O", "S"), max_iters=30)
    whole = run_study(cfg)
    parts = run_study(cfg, chunk=3)
    assert whole.timings["chunks"] == 1 and parts.timings["chunks"] == 4
    for k in _study.CSV_COLUMNS:
        if k != "seconds":
            np.testing.assert_array_equal(whole.columns[k], parts.columns[k], err_msg=k)
    for key in whole.histories:
        np.testing.assert_array_equal(whole.histories[key], parts.histories[key])
    monkeypatch.setattr(_study, "HISTORY_TRIALS", 2)
    capped = run_study(cfg, chunk=4)
    angle, _ = _study.history_labels(cfg)
    assert capped.histories[("inv", "O")].shape == (4, cfg.max_iters + 1) and len(angle) == 4
    np.testing.assert_array_equal(capped.histories[("inv", "O")],
                                  whole.histories[("inv", "O")][[0, 1, 5, 6]])
    assert len(capped) == len(whole) == 20
    with pytest.raises(ValueError, match="chunk"):
        run_study(cfg, chunk=0)


def test_a_stalled_compilation_ends_in_an_error_naming_the_setting(monkeypatch, tmp_path):
    """The watchdog on the study's compilation: past ``SPDSLAM_COMPILE_TIMEOUT`` seconds
    ``run_study`` raises, and ``spdslam simulate`` says so on one line with exit status 2,
    instead of hanging (the stalled compile thread is a daemon)."""
    import time

    from spdslam.solver._batched import BatchedProblem

    monkeypatch.setenv("SPDSLAM_COMPILE_TIMEOUT", "0.5")
    monkeypatch.setattr(BatchedProblem, "compile", lambda self, *a, **k: time.sleep(30))
    cfg = StudyConfig(trials=1, angles=(120.0,), noise=("L",), models=("inv",), params=("O",), max_iters=5)
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="optimize"):
        run_study(cfg)
    assert time.perf_counter() - t0 < 10
    res = cli_runner().invoke(app, ["simulate", "--out", str(tmp_path / "x"), "--trials", "1",
                                    "--angles", "120", "--noise", "L", "--models", "inv", "--params", "O"])
    assert res.exit_code == 2 and "did not finish" in res.output, res.output
    assert not (tmp_path / "x").exists()
