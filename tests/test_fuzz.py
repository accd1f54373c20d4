"""Fuzzing the readers (issue 15): a valid sequence folder corrupted at random, and a fixed
corpus of corruptions; each read either parses or raises the documented one-line
``SequenceFormatError`` — never another exception.

The corpus (``corpus()``: every mutation of every file of a canonical folder and of an
OA-SLAM layout, with fixed seeds: 216 and 180 cases) runs in the default suite, with a
short hypothesis run; ``-m slow`` adds a longer one. Every corruption the readers refuse is
also given to ``spdslam run``: one line, exit 2, nothing written, the input untouched.
"""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spdslam.io import SequenceFormatError, read_sequence, write_sequence
from spdslam.synthetic import make_room_sequence

FILES = ("camera.yaml", "trajectory.txt", "detections.txt", "objects_gt.txt", "groundtruth.txt",
         "priors.yaml")
#: Tokens that a corrupted file may hold where a number belongs.
BAD_TOKENS = ("nan", "inf", "-inf", "1e400", "-1e300", "1e-320", "0", "-0", "", "x", "1_0",
              "0x10", "'5'", "\"5\"", "[]", "{}", "~", "null", "true", "1e3", "-", "١٢")


def _lines(text: str) -> list[str]:
    return text.split("\n")


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """One corruption of a file's bytes (``kind`` among ``MUTATIONS``)."""
    text = data.decode("utf-8", errors="replace")
    lines = _lines(text)
    i = rng.randrange(len(lines)) if lines else 0
    if kind == "truncate":
        return data[: rng.randrange(len(data) + 1)]
    if kind == "delete_line":
        del lines[i]
    elif kind == "duplicate_line":
        lines.insert(i, lines[i])
    elif kind == "delete_column":
        tok = lines[i].split()
        if tok:
            del tok[rng.randrange(len(tok))]
        lines[i] = " ".join(tok)
    elif kind == "duplicate_column":
        tok = lines[i].split()
        if tok:
            tok.insert(rng.randrange(len(tok)), rng.choice(tok))
        lines[i] = " ".join(tok)
    elif kind == "swap_tokens":
        tok = lines[i].split()
        if len(tok) > 1:
            a, b = rng.sample(range(len(tok)), 2)
            tok[a], tok[b] = tok[b], tok[a]
        lines[i] = " ".join(tok)
    elif kind == "bad_token":
        tok = lines[i].split()
        if tok:
            tok[rng.randrange(len(tok))] = rng.choice(BAD_TOKENS)
        lines[i] = " ".join(tok)
    elif kind == "huge_number":
        tok = lines[i].split()
        if tok:
            tok[rng.randrange(len(tok))] = rng.choice(("1e300", "-1e300", "1e308", "5e-324", "-1"))
        lines[i] = " ".join(tok)
    elif kind == "bytes":
        k = rng.randrange(len(data) + 1)
        return data[:k] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 8))) + data[k:]
    elif kind == "bom":
        return b"\xef\xbb\xbf" + data.replace(b"\n", b"\r\n")
    elif kind == "empty":
        return b""
    elif kind == "yaml_junk":
        lines.insert(i, rng.choice(("- a", "key: [1, 2", "{", "&a [*a]", "!!python/object:os.system x",
                                    "fx: 1\nfx: 2", "\t- tab")))
    else:
        raise ValueError(kind)
    return "\n".join(lines).encode("utf-8")


MUTATIONS = ("truncate", "delete_line", "duplicate_line", "delete_column", "duplicate_column",
             "swap_tokens", "bad_token", "huge_number", "bytes", "bom", "empty", "yaml_junk")


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz") / "seq"
    write_sequence(make_room_sequence(0, frames=6, objects=1), folder)
    priors = folder / "priors.yaml"
    if not priors.exists():
        priors.write_text("up: [0, 0, 1]\nsupport_planes:\n  - [0, 0, 1, 0]\n", encoding="utf-8")
    return folder


#: The files of the OA-SLAM layout (real recordings: ``import_oaslam``).
OASLAM_FILES = ("cam.yaml", "odometry.txt", "groundtruth.txt", "detections_yolo.json", "objects_gt.txt")


@pytest.fixture(scope="module")
def valid_oaslam(tmp_path_factory) -> Path:
    """A small OA-SLAM layout: an orbit of 12 poses, one cup seen in each frame."""
    folder = tmp_path_factory.mktemp("fuzz") / "oaslam"
    folder.mkdir()
    n = 12
    ts = 100.0 + 0.1 * np.arange(n)
    a = np.linspace(0, np.pi / 3, n)
    rows = []
    for t, ang in zip(ts, a):
        c = [2 * np.cos(ang), 2 * np.sin(ang), 0.0]
        z = -np.array(c) / 2.0  # optical axis towards the origin, x horizontal, y down
        x = np.array([-np.sin(ang), np.cos(ang), 0.0])
        R = np.column_stack([x, np.cross(z, x), z])
        from scipy.spatial.transform import Rotation

        rows.append([t, *c, *Rotation.from_matrix(R).as_quat()])
    tum = "".join(" ".join(repr(float(v)) for v in r) + "\n" for r in rows)
    (folder / "odometry.txt").write_text(tum)
    (folder / "groundtruth.txt").write_text(tum)
    (folder / "cam.yaml").write_text("%YAML:1.0\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\n"
                                     "Camera.cy: 240\nCamera.k1: 0.1\nCamera.k2: -0.05\n")
    dets = [{"file_name": f"{float(t)!r}.png", "detections": [
        {"category_id": 41, "detection_score": 0.9, "bbox": [290.0, 210.0, 350.0, 270.0]}]} for t in ts]
    (folder / "detections_yolo.json").write_text(json.dumps(dets, indent=1))
    (folder / "objects_gt.txt").write_text("cup 0 0 0 0 0 0 0.05 0.05 0.1 41:cup\n")
    read_sequence(folder)  # valid before it is corrupted
    return folder


#: The files of a detector's output folder (``import_detector_folder``): YOLO labels beside a
#: ROS camera_info, COCO results beside a Kalibr camchain.
YOLO_FILES = ("camera.yaml", "trajectory.txt", "rgb.txt", "labels/img_00000.txt", "data.yaml")
COCO_FILES = ("camera.yaml", "trajectory.txt", "coco_results.json", "coco_images.json")
LAYOUT_FILES = {"canonical": FILES, "oaslam": OASLAM_FILES, "yolo": YOLO_FILES, "coco": COCO_FILES}


@pytest.fixture(scope="module")
def folders(valid, valid_oaslam, tmp_path_factory) -> dict:
    """{layout: a valid folder of it}: the canonical and OA-SLAM ones, and the canonical
    sequence written as a detector's output folder both ways."""
    from conftest import write_detector_folder

    seq = read_sequence(valid)
    base = tmp_path_factory.mktemp("fuzz")
    out = {"canonical": valid, "oaslam": valid_oaslam,
           "yolo": write_detector_folder(seq, base / "yolo", detector="yolo", calibration="ros"),
           "coco": write_detector_folder(seq, base / "coco", detector="coco", calibration="kalibr")}
    from spdslam.io import COCO80

    if not (out["yolo"] / "data.yaml").exists():  # Ultralytics' names, as a list
        (out["yolo"] / "data.yaml").write_text("names: [" + ", ".join(COCO80) + "]\n", encoding="utf-8")
    for layout in ("yolo", "coco"):
        assert all((out[layout] / f).is_file() for f in LAYOUT_FILES[layout]), layout
        read_sequence(out[layout])  # valid before it is corrupted
    return out


def corpus(n_seeds: int = 3) -> list[tuple[str, str, str, int]]:
    """(layout, file, mutation, seed): every mutation of every file of every layout
    (``LAYOUT_FILES``), ``n_seeds`` seeds each."""
    return [(layout, f, m, s) for layout, files in LAYOUT_FILES.items() for f in files
            for m in MUTATIONS for s in range(n_seeds)]


def check_read(folder: Path) -> str:
    """"ok" or "error": ``read_sequence`` parses, or raises a one-line ``SequenceFormatError``
    that names a file; any other exception fails the test."""
    try:
        seq = read_sequence(folder)
    except SequenceFormatError as e:
        msg = str(e)
        assert "\n" not in msg and msg.strip(), repr(msg)
        assert str(folder) in msg, msg
        return "error"
    assert np.all(np.isfinite(seq.poses_tum)) and np.all(np.isfinite(seq.timestamps))
    assert np.allclose(np.linalg.norm(seq.poses_tum[:, 3:7], axis=1), 1.0)
    for d in seq.detections:
        assert d.box[2] > d.box[0] and d.box[3] > d.box[1]
    return "ok"


def _corrupted(valid: Path, tmp: Path, fname: str, kind: str, seed: int) -> Path:
    folder = tmp / f"{valid.name}-{fname.replace('/', '_')}-{kind}-{seed}"
    shutil.copytree(valid, folder)
    p = folder / fname
    p.write_bytes(mutate(p.read_bytes(), kind, random.Random(f"{fname}{kind}{seed}")))
    return folder


def test_corpus_has_at_least_140_cases_per_layout():
    layouts = [c[0] for c in corpus()]
    assert all(layouts.count(layout) >= 140 for layout in LAYOUT_FILES)


def test_every_corrupted_file_parses_or_gives_the_one_line_error(folders, tmp_path):
    outcomes = {}
    for layout, fname, kind, seed in corpus():
        folder = _corrupted(folders[layout], tmp_path, fname, kind, seed)
        outcomes[(layout, fname, kind, seed)] = check_read(folder)
        shutil.rmtree(folder)
    for layout in LAYOUT_FILES:
        mine = {k: v for k, v in outcomes.items() if k[0] == layout}
        errors = sum(v == "error" for v in mine.values())
        # the corruptions bite: most are errors, and the harmless ones (a BOM, CRLF) parse
        assert errors >= len(mine) // 2, (layout, errors)
    assert all(v == "ok" for k, v in outcomes.items() if k[2] == "bom"), \
        [k for k, v in outcomes.items() if k[2] == "bom" and v != "ok"]


def _fuzz(valid: Path, tmp: Path, fname: str, kinds: list, seed: int) -> None:
    folder = tmp / "case"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(valid, folder)
    p = folder / fname
    rng = random.Random(seed)
    data = p.read_bytes()
    for kind in kinds:
        data = mutate(data, kind, rng)
    p.write_bytes(data)
    check_read(folder)


_CASES = st.sampled_from([(layout, f) for layout, files in LAYOUT_FILES.items() for f in files])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=_CASES, kinds=st.lists(st.sampled_from(MUTATIONS), min_size=1, max_size=3),
       seed=st.integers(0, 2**32 - 1))
def test_random_corruptions(folders, tmp_path, case, kinds, seed):
    _fuzz(folders[case[0]], tmp_path, case[1], kinds, seed)


@pytest.mark.slow
@settings(max_examples=2000, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=_CASES, kinds=st.lists(st.sampled_from(MUTATIONS), min_size=1, max_size=5),
       seed=st.integers(0, 2**32 - 1))
def test_random_corruptions_long(folders, tmp_path, case, kinds, seed):
    _fuzz(folders[case[0]], tmp_path, case[1], kinds, seed)


def test_the_cli_gives_one_line_and_writes_nothing_for_every_refused_corruption(folders, tmp_path):
    """``spdslam run`` (and ``spdslam import`` for the OA-SLAM layout) on each corrupted
    folder that the readers refuse: exit 2, one line ``spdslam: error: …`` on stderr, no
    traceback, no output folder, the input untouched."""
    from conftest import cli_runner

    from spdslam import cli

    runner = cli_runner()
    refused = 0
    for layout, fname, kind, seed in corpus():
        folder = _corrupted(folders[layout], tmp_path, fname, kind, seed)
        try:
            read_sequence(folder)
            shutil.rmtree(folder)
            continue  # parses: mapping it is the other tests' work
        except SequenceFormatError:
            pass
        before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
        out = tmp_path / "out"
        commands = [["run", str(folder), "--out", str(out)]]
        if layout == "oaslam":  # the importer reads the same files (the detector's: tests/test_detector_folder.py)
            commands.append(["import", str(folder), str(out)])
        for args in commands:
            res = runner.invoke(cli.app, args)
            assert res.exit_code == 2 and isinstance(res.exception, SystemExit), (args, fname, kind, res.exception)
            lines = res.stderr.splitlines()
            assert len(lines) == 1 and lines[0].startswith("spdslam: error: "), res.stderr
            assert not out.exists()
        assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before
        shutil.rmtree(folder)
        refused += 1
    print(f"spdslam run: {refused} refused corruptions, each one line and exit 2, nothing written")
    assert refused >= 300, refused


def test_evaluate_on_every_corrupted_ground_truth(valid, valid_oaslam, tmp_path):
    """``spdslam evaluate`` of a good map against each corrupted ground-truth file of the
    corpus (``groundtruth.txt``, ``objects_gt.txt``; both layouts): strict JSON metrics and
    exit 0, or one line and exit 2 with the run's files untouched — never a traceback."""
    from conftest import cli_runner, write_truth_run

    from spdslam import cli

    runner = cli_runner()
    bases = {}
    for layout, src in (("canonical", valid), ("oaslam", valid_oaslam)):  # a good map of each
        bases[layout] = write_truth_run(read_sequence(src), tmp_path / f"map-{layout}")
        res = runner.invoke(cli.app, ["evaluate", str(bases[layout]), str(src)])
        assert res.exit_code == 0, res.output
    counts = {"evaluated": 0, "refused": 0}
    for layout, fname, kind, seed in corpus():
        if fname not in ("groundtruth.txt", "objects_gt.txt"):
            continue
        folder = _corrupted(valid if layout == "canonical" else valid_oaslam, tmp_path, fname, kind, seed)
        out = bases[layout]
        before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
        res = runner.invoke(cli.app, ["evaluate", str(out), str(folder)])
        assert res.exit_code in (0, 2) and isinstance(res.exception, (SystemExit, type(None))), \
            (layout, fname, kind, seed, res.exception)
        if res.exit_code == 2:
            lines = res.stderr.splitlines()
            assert len(lines) == 1 and lines[0].startswith("spdslam: error: "), res.stderr
            assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
            counts["refused"] += 1
        else:
            json.loads((out / "metrics.json").read_text(encoding="utf-8"),
                       parse_constant=lambda c: pytest.fail(f"non-strict JSON token {c}"))
            counts["evaluated"] += 1
        shutil.rmtree(folder)
    print(f"spdslam evaluate: {counts}")
    assert counts["refused"] >= 40 and counts["evaluated"] >= 10, counts
