"""Ray as the execution engine, on a local Ray instance of 2 CPUs (the ray extra; skipped
without it): the same trials.csv and maps as the run without Ray, and failing tasks reported
with their error while the others finish.

These cases start Ray's daemons from the test process, so ``tests/test_ray.py`` runs them in
a pytest process of their own: a Ray process that ends its driver (Ray exits the driver at
once when it loses its raylet) then fails one test with Ray's output instead of taking a
test worker, and the run's scheduling, down with it. ``python3 -m pytest tests/ray_cases.py``
runs them directly."""

from __future__ import annotations

import csv
import json
import sys

import pytest
from conftest import cli_invoke

ray = pytest.importorskip("ray")

from spdslam.experiments import RayEngine, StudyConfig, run_study  # noqa: E402
from spdslam.io import write_sequence  # noqa: E402
from spdslam.synthetic import make_room_sequence  # noqa: E402

# the workers cannot import this test module: its functions travel by value
ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def engine():
    """One local Ray instance for the module (the engines made by the CLI join it)."""
    if ray.is_initialized():
        ray.shutdown()
    e = RayEngine(workers=2)
    yield e
    e.close()


def _flaky(x, marker):
    """Fails the first time it sees ``x == 1`` (a file records it), then succeeds."""
    import pathlib

    if x == 1 and not pathlib.Path(marker).exists():
        pathlib.Path(marker).write_text("failed once")
        raise RuntimeError("transient")
    if x == 2:
        raise ValueError("always fails")
    return x + 100


def test_failing_tasks_are_retried_and_reported_and_the_others_finish(engine, tmp_path):
    marker = str(tmp_path / "seen")
    seen = []
    outcomes = engine.map(_flaky, [(0, marker), (1, marker), (2, marker), (3, marker)],
                          on_outcome=seen.append)
    assert [o.value for o in outcomes] == [100, 101, None, 103]
    assert outcomes[1].ok and outcomes[1].attempts == 2  # retried once, then it worked
    assert outcomes[2].error == "ValueError: always fails" and outcomes[2].attempts == 2
    assert sorted(o.index for o in seen) == [0, 1, 2, 3]
    assert all(":" in o.where for o in outcomes)  # host:pid of the Ray worker


def _strip_seconds(path):
    with open(path) as f:
        rows = list(csv.reader(f))
    k = rows[0].index("seconds")
    return [r[:k] + r[k + 1:] for r in rows]


def test_simulate_on_ray_writes_the_trials_of_the_local_run(engine, tmp_path):
    args = ["simulate", "--trials", "20", "--angles", "60", "--noise", "M,H", "--params", "S,O",
            "--models", "semi", "--max-iters", "60"]
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    r = cli_invoke(*args, "--out", local)
    assert r.exit_code == 0, r.output
    r = cli_invoke(*args, "--out", on_ray, "--ray", "--trials-per-task", "16")
    assert r.exit_code == 0, r.output
    assert "on Ray (2 CPUs)" in r.output
    a, b = _strip_seconds(local / "trials.csv"), _strip_seconds(on_ray / "trials.csv")
    assert len(a) == 1 + 2 * 2 * 20 and a == b  # every column but the seconds
    summary = json.loads((on_ray / "summary.json").read_text())
    # 40 problems per method in tasks of 16: 3 tasks each, the last padded
    assert summary["timings"]["tasks"] == 6 and summary["timings"]["engine"] == "ray"


def test_study_on_ray_equals_the_local_study_with_histories(engine):
    import numpy as np

    cfg = StudyConfig(trials=16, angles=(120.0,), noise=("H",), params=("F", "O"), models=("inv",),
                      max_iters=40)
    a = run_study(cfg)
    b = run_study(cfg, engine=engine)  # default task size: at least 16 problems
    drop = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]  # noqa: E731
    assert drop(a.rows) == drop(b.rows)
    for k in a.histories:
        np.testing.assert_array_equal(a.histories[k], b.histories[k])


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = tmp_path_factory.mktemp("rayroom")
    write_sequence(make_room_sequence(5, 30, 2), root / "room")
    return root


@pytest.mark.slow  # maps on Ray workers (35 s); the tests above run the engine's tasks in the default suite
def test_batch_on_ray_writes_the_maps_of_the_local_batch(engine, room, tmp_path):
    m = room / "m.yaml"
    m.write_text("""\
jobs:
  - sequence: room
    method: multi-spd
  - sequence: room
    name: raises
    hold_trajectory: true
    min_views: 1000
""")  # no object and every pose held: "optimisation (inverse boxes): the graph has no factors"
    local, on_ray = tmp_path / "local", tmp_path / "ray"
    r = cli_invoke("batch", m, "--out", local, "--retries", "0")
    assert r.exit_code == 1, r.output
    r = cli_invoke("batch", m, "--out", on_ray, "--ray")
    assert r.exit_code == 1, r.output
    rows = list(csv.DictReader(open(on_ray / "batch.csv")))
    assert [x["status"] for x in rows] == ["done", "failed"]
    assert rows[1]["stage"] == "map" and rows[1]["attempts"] == "2"  # tried again, reported
    assert rows[1]["error"] == list(csv.DictReader(open(local / "batch.csv")))[1]["error"]
    assert "optimisation (inverse boxes): the graph has no factors" in rows[1]["error"]
    assert "raises failed (map, 2 attempts)" in r.stderr
    for job in ("room-multi-spd",):
        for f in ("map.json", "trajectory.txt", "metrics.json", "report.md"):
            assert (local / job / f).read_bytes() == (on_ray / job / f).read_bytes(), (job, f)


@pytest.mark.slow  # maps on Ray workers (35 s)
def test_compare_on_ray_writes_the_local_table(engine, room, tmp_path):
    import shutil

    seq = tmp_path / "seq"
    shutil.copytree(room / "room", seq)
    a, b = tmp_path / "a", tmp_path / "b"
    assert cli_invoke("compare", seq, "--methods", "multi-rts,multi-spd", "--out", a).exit_code == 0
    r = cli_invoke("compare", seq, "--methods", "multi-rts,multi-spd", "--out", b, "--ray")
    assert r.exit_code == 0, r.output
    assert (a / "table.md").read_text() == (b / "table.md").read_text()
