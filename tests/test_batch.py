"""Batches of sequence runs without Ray: the manifest's reading and its errors (file:line),
the local engine's failure handling, and ``spdslam batch`` in this process."""

from __future__ import annotations

import csv
import json

import pytest
from conftest import cli_invoke

from spdslam.experiments import LocalEngine, read_manifest
from spdslam.io import SequenceFormatError, write_sequence
from spdslam.mapping import OnlineSettings, RunSettings
from spdslam.synthetic import make_room_sequence


def _manifest(tmp_path, text: str):
    p = tmp_path / "m.yaml"
    p.write_text(text, encoding="utf-8")
    return p


def test_a_manifest_expands_methods_and_applies_defaults(tmp_path):
    (tmp_path / "seqs" / "a").mkdir(parents=True)
    p = _manifest(tmp_path, """\
defaults:
  max_iterations: 40
  sigma: {inverse_box: 3}
jobs:
  - sequence: seqs/a
    methods: [multi-rts, multi-spd]
  - sequence: seqs/a
    name: a-online
    robust: [huber]
    online: {window: 12}
    max_iterations: 7
""")
    jobs = read_manifest(p)
    assert [j.name for j in jobs] == ["a-multi-rts", "a-multi-spd", "a-online"]
    assert [j.method for j in jobs] == ["multi-rts", "multi-spd", "multi-spd"]
    assert jobs[0].sequence == tmp_path / "seqs" / "a"
    assert jobs[0].settings == RunSettings.of("multi-rts", max_iterations=40, sigma={"inverse_box": 3.0})
    assert jobs[2].settings.max_iterations == 7
    assert jobs[2].settings.online == OnlineSettings(window=12)
    assert (jobs[2].settings.method.robust, jobs[2].settings.method.robust_k) == ("huber", 1.0)
    assert [j.line for j in jobs] == [5, 5, 7]


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("jobs:\n  - sequence: a\n    method: nope\n", 3, "a method among"),
        ("jobs:\n  - sequence: a\n    colour: red\n", 3, "a key of a job among"),
        ("jobs:\n  - method: multi-spd\n", 2, "a sequence for the job"),
        ("jobs:\n  - sequence: a\n  - sequence: a\n", 3, "unique job names"),
        ("jobs:\n  - sequence: a\n    sigma: {inverse_box: -1}\n", 3, "sigma: expected a finite positive value for inverse_box"),
        ("jobs:\n  - sequence: a\n    sigma: {nonsense: 1}\n", 3, "a sigma among"),
        ("jobs:\n  - sequence: a\n    online: true\n    keyframes: 3\n", 4, "keyframes: an online run uses every frame: expected all, got 3"),
        ("jobs:\n  - sequence: a\n    parameterization: full\n    online: true\n", 3,
         "parameterization: online mapping takes SPD or RTS landmarks: expected spd or rts, got 'full'"),
        ("defaults:\n  max_iterations: 0\njobs:\n  - sequence: a\n", 2, "max_iterations: expected an integer ≥ 1, got 0"),
        ("jobs:\n  - sequence: a\n    tolerance: -1\n", 3, "tolerance: expected a finite number ≥ 0"),
        ("jobs:\n  - sequence: a\n    orientation: sideways\n", 3, "orientation: must be one of improved"),
        ("jobs:\n  - sequence: a\n    truncation_margin: wide\n", 3, "truncation_margin: expected a number, got 'wide'"),
        ("jobs:\n  - sequence: a\n    robust: [3]\n", 3, "robust: expected KERNEL or a list"),
        ("jobs:\n  - sequence: a\n    sigma: [1]\n", 3, "sigma: expected a mapping NAME: VALUE"),
        ("jobs:\n  - sequence: a\n    name: x/y\n", 3, "a plain folder name"),
        ("jobs:\n  - sequence: a\n    methods: [multi-spd, multi-rts]\n    name: n\n", 4, "no name for a job of several methods"),
        ("jobs:\n  - sequence: a\n    max_iterations: 0\n", 3, "an integer ≥ 1"),
        ("jobs:\n  - sequence: a\n    robust: [bogus]\n", 3, "robust: expected KERNEL"),
        ("jobs:\n  - sequence: a\n    online: {window: 1}\n", 3, "online.window: expected an integer ≥ 2, got 1"),
        ("jobs:\n  - sequence: a\n    online:\n      every: 2\n      window: 1\n", 5, "online.window: expected an integer ≥ 2"),
        ("jobs: []\n", 1, "a non-empty list of jobs"),
        ("defaults:\n  sequence: a\njobs:\n  - sequence: a\n", 2, "defaults without sequence or name"),
        ("jobs:\n  - sequence: a\n    method: multi-spd\n    methods: [multi-rts]\n", 4, "method or methods, not both"),
        ("jobz:\n  - sequence: a\n", 1, "a key of the manifest among defaults, jobs"),
        ("jobs:\n  - sequence: a\n  bad indent\n", 4, "valid YAML"),  # the mark PyYAML gives
    ],
)
def test_a_malformed_manifest_names_its_line(tmp_path, text, line, words):
    p = _manifest(tmp_path, text)
    with pytest.raises(SequenceFormatError) as e:
        read_manifest(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}: "), msg
    assert words in msg and "\n" not in msg


def test_a_manifest_without_jobs_and_a_missing_manifest(tmp_path):
    with pytest.raises(SequenceFormatError, match="a list of jobs"):
        read_manifest(_manifest(tmp_path, "defaults: {max_iterations: 3}\n"))
    with pytest.raises(SequenceFormatError, match="no such file"):
        read_manifest(tmp_path / "absent.yaml")


def _boom(x):
    if x == 2:
        raise ValueError("two\nis   bad")
    return x * 10


def test_the_local_engine_reports_a_failing_task_and_finishes_the_others():
    seen = []
    outcomes = LocalEngine(retries=2).map(_boom, [(1,), (2,), (3,)], on_outcome=seen.append)
    assert [o.value for o in outcomes] == [10, None, 30]
    bad = outcomes[1]
    assert not bad.ok and bad.attempts == 3 and bad.error == "ValueError: two is bad"
    assert [o.index for o in seen] == [0, 1, 2]


@pytest.fixture(scope="module")
def two_sequences(tmp_path_factory):
    """A small demo room written twice: a good sequence and one with a malformed line."""
    root = tmp_path_factory.mktemp("batch")
    seq = make_room_sequence(3, 30, 2)
    write_sequence(seq, root / "room")
    write_sequence(seq, root / "broken")
    det = root / "broken" / "detections.txt"
    lines = det.read_text().splitlines()
    lines[2] = "not a detection"
    det.write_text("\n".join(lines) + "\n")
    return root


def test_batch_runs_the_good_jobs_and_reports_the_bad_ones(two_sequences, tmp_path, monkeypatch):
    m = _manifest(two_sequences, """\
jobs:
  - sequence: room
    method: multi-spd
  - sequence: broken
  - sequence: room
    name: crash
""")
    import spdslam.mapping

    real = spdslam.mapping.run_sequence

    def crash(seq, settings, **kw):  # a failure of the whole problem, in the job "crash"
        if crash.calls:
            raise spdslam.mapping.MappingError("optimisation (inverse boxes)", "Singular matrix")
        crash.calls += 1
        return real(seq, settings, **kw)

    crash.calls = 0
    monkeypatch.setattr(spdslam.mapping, "run_sequence", crash)
    out = tmp_path / "out"
    r = cli_invoke("batch", m, "--out", out, "--retries", "0")
    assert r.exit_code == 1, r.output
    rows = list(csv.DictReader(open(out / "batch.csv")))
    assert [x["job"] for x in rows] == ["room-multi-spd", "broken-multi-spd", "crash"]
    assert [x["status"] for x in rows] == ["done", "failed", "failed"]
    assert [x["stage"] for x in rows] == ["", "read", "map"]
    assert "detections.txt:3:" in rows[1]["error"]
    assert "optimisation (inverse boxes): Singular matrix" in rows[2]["error"]
    assert (out / "room-multi-spd" / "map.json").is_file()
    assert not (out / "broken-multi-spd").exists() and not (out / "crash").exists()
    report = json.loads((out / "batch.json").read_text())
    assert report["engine"]["name"] == "local" and len(report["jobs"]) == 3
    assert float(rows[0]["mean_iou"]) > 0.5
    # the same run through spdslam run: the same map
    monkeypatch.undo()
    single = tmp_path / "single"
    r = cli_invoke("run", two_sequences / "room", "--out", single, "--no-overlay")
    assert r.exit_code == 0, r.output
    a = json.loads((single / "map.json").read_text())
    b = json.loads((out / "room-multi-spd" / "map.json").read_text())
    assert a["objects"] == b["objects"] and a["final_cost"] == b["final_cost"]


def test_batch_refuses_bad_options_in_one_line(two_sequences, tmp_path):
    m = _manifest(two_sequences, "jobs:\n  - sequence: room\n")
    r = cli_invoke("batch", m, "--out", tmp_path / "o", "--workers", "2")
    assert r.exit_code == 2 and "--workers" in r.stderr and "--ray" in r.stderr
    bad = _manifest(tmp_path, "jobs:\n  - sequence: room\n    method: x\n")
    r = cli_invoke("batch", bad, "--out", tmp_path / "o")
    assert r.exit_code == 2 and f"{bad}:3:" in r.stderr
    r = cli_invoke("simulate", "--trials", "2", "--trials-per-task", "4", "--out", tmp_path / "s")
    assert r.exit_code == 2 and "--trials-per-task" in r.stderr


def test_the_manifest_of_docs_scaling_md_reads(tmp_path):
    """docs/scaling.md's example manifest is one the reader takes, with the jobs it says."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "scaling.md").read_text(encoding="utf-8")
    block = text.split("```yaml\n", 1)[1].split("```", 1)[0]
    jobs = read_manifest(_manifest(tmp_path, block))
    assert [j.name for j in jobs] == ["room0-quadric-slam", "room0-multi-rts", "room0-multi-spd",
                                      "room1-online"]
    assert jobs[3].settings.online.window == 30 and jobs[3].settings.sigma == {"inverse_box": 3.0}


def test_a_job_overrides_any_field_of_its_method(tmp_path):
    p = _manifest(tmp_path, "jobs:\n  - sequence: a\n    orientation: none\n    robust_builtin_priors: false\n")
    (job,) = read_manifest(p)
    assert job.settings.method.orientation == "none" and job.settings.method.robust_builtin_priors is False
