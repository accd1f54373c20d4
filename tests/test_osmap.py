"""Saved maps of other systems (issue 49): the map-format registry and Osmap maps (GOReloc,
VOOM): objects as dual quadrics with category histograms, keyframes' T_cw and times.

The Osmap files here are written by ``write_osmap`` with the reader's own schema
(``io.osmap_messages``), so that the reader is checked against the layout, not against
itself: Q* is written as the systems write it (row major, scaled by an arbitrary factor),
T_cw as the first 12 floats of the row-major 4×4 matrix. GOReloc's published fr2_desk map is
read when it is there (``SPDSLAM_GORELOC_MAP``, benchmarks/peer_maps.py)."""

from __future__ import annotations

import json
import os
import random
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error as assert_error
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from scipy.spatial.transform import Rotation

from spdslam import Ellipsoid
from spdslam.io import (
    COCO80,
    MAP_FORMATS,
    MapFormatError,
    MapObject,
    find_map_format,
    load_map,
    map_document,
    osmap_messages,
    write_map,
    write_sequence,
)
from spdslam.mapping import moved_sequence, transform_ellipsoid
from spdslam.synthetic import make_room_sequence


def _dual(e: Ellipsoid, scale: float) -> np.ndarray:
    """scale · Q* (4×4) of an ellipsoid, Q* = [[P − ttᵀ, −t], [−tᵀ, −1]]."""
    P, t = np.asarray(e.P), np.asarray(e.center)
    Q = np.block([[P - np.outer(t, t), -t[:, None]], [-t[None, :], -np.ones((1, 1))]])
    return scale * Q


def write_osmap(folder: Path, objects, keyframes=(), graphs=None, name: str = "map",
                counts: dict | None = None, quadrics: dict | None = None, oa_slam: bool = False) -> Path:
    """An Osmap map in ``folder``: ``objects`` [(id, ellipsoid, {category id: count})],
    ``keyframes`` [(id, timestamp, T_wc 4×4)], ``graphs`` [[(category id, object id)]]
    (nodes per keyframe; not written when None); ``counts`` overrides the header's counts,
    ``quadrics`` {index: 16 numbers} an object's Q* entries. ``oa_slam``: OA-SLAM's layout
    (map objects with their track's id, the tracks' categories (the most counted), the
    keyframes' times as seconds and nanoseconds). Returns the header."""
    M = osmap_messages()
    folder.mkdir(parents=True, exist_ok=True)
    oa = M["SerializedObjectArray"]()
    tracks = M["SerializedObjectTrackArray"]()
    for k, (oid, e, cats) in enumerate(objects):
        o = oa.object.add()
        o.object_id = oid
        q = (quadrics or {}).get(k)
        o.ellipsoid.element.extend(q if q is not None else _dual(e, -0.5 - k).reshape(-1).tolist())
        if oa_slam:
            tr = tracks.objecttrack.add()
            tr.id, tr.cat = oid, max(cats, key=cats.get)
        else:
            o.cat_ids.extend(list(cats))
            o.cat_counts.extend(list(cats.values()))
    ka = M["SerializedKeyframeStampedArray" if oa_slam else "SerializedKeyframeArray"]()
    for kid, stamp, T_wc in keyframes:
        kf = ka.keyframe.add()
        kf.id = kid
        if oa_slam:
            kf.timestamp.sec = int(np.floor(stamp))
            kf.timestamp.nsec = int(round((stamp - np.floor(stamp)) * 1e9))
        else:
            kf.timestamp = stamp
        kf.pose.element.extend(np.linalg.inv(T_wc)[:3].reshape(-1).tolist())
    if oa_slam:
        (folder / f"{name}.mapobjects").write_bytes(oa.SerializeToString())
        (folder / f"{name}.objecttracks").write_bytes(tracks.SerializeToString())
        lines = ["%YAML:1.0", "---", f'mapobjectsFile: "{name}.mapobjects"', f"nMapobjects: {len(objects)}",
                 f'objecttracksFile: "{name}.objecttracks"', f"nObjectTracks: {len(objects)}"]
    else:
        (folder / f"{name}.objects").write_bytes(oa.SerializeToString())
        lines = ["%YAML:1.0", "---", f'objectsFile: "{name}.objects"', f"nObjects: {len(objects)}"]
    if keyframes:
        (folder / f"{name}.keyframes").write_bytes(ka.SerializeToString())
        lines += [f'keyframesFile: "{name}.keyframes"', f"nKeyframes: {len(keyframes)}"]
    if graphs is not None:
        ga = M["SerializedGraphArray"]()
        for nodes in graphs:
            g = ga.graph.add()
            for j, (cat, oid) in enumerate(nodes):
                nd = g.node.add()
                nd.node_id, nd.category_id, nd.object_id = j, cat, oid
        (folder / f"{name}.graphs").write_bytes(ga.SerializeToString())
        lines += [f'graphsFile: "{name}.graphs"', f"nGraphs: {len(graphs)}"]
    for key, value in (counts or {}).items():
        lines = [ln for ln in lines if not ln.startswith(key + ":")] + [f"{key}: {value}"]
    lines += ["cameraMatrices:", "   - { fx:5.2e+02, fy:5.2e+02,", "       cx:3.2e+02, cy:2.4e+02 }"]
    header = folder / f"{name}.yaml"
    header.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return header


def _random_ellipsoid(rng) -> Ellipsoid:
    R = Rotation.random(random_state=rng).as_matrix()
    return Ellipsoid.from_axes(R, rng.uniform(-3, 3, 3), rng.uniform(0.03, 0.6, 3))


def _pose(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-2, 2, 3)
    return T


def test_objects_keyframes_and_labels_read_back(tmp_path):
    rng = np.random.default_rng(0)
    es = [_random_ellipsoid(rng) for _ in range(4)]
    objs = [(7, es[0], {66: 3, 64: 5}), (2, es[1], {62: 9}), (11, es[2], {}), (5, es[3], {})]
    poses = [_pose(rng) for _ in range(5)]
    stamps = [3.0, 1.0, 2.5, 4.0, 0.5]  # written out of order: read sorted by time
    kfs = [(i + 1, s, T) for i, (s, T) in enumerate(zip(stamps, poses))]
    graphs = [[(41, 11), (41, 11), (39, 11), (56, 2 ** 32 - 1)], [(39, 99)]]
    header = write_osmap(tmp_path / "m", objs, kfs, graphs)
    m = load_map(header)
    assert m.format == "osmap" and not m.is_spdslam and m.path == header
    assert [o.id for o in m.objects] == [7, 2, 11, 5]
    # the most counted category; else the graph nodes' most frequent; else "object", noted
    assert [o.label for o in m.objects] == ["mouse", "tv", "cup", "object"]
    assert any("1 objects carry no category" in n and "[5]" in n for n in m.notes)
    for o, e in zip(m.objects, es):  # float32 on disk
        np.testing.assert_allclose(o.ellipsoid.center, e.center, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(o.ellipsoid.P, e.P, rtol=1e-4, atol=2e-6)
    order = np.argsort(stamps)
    np.testing.assert_allclose(m.trajectory[:, 0], np.sort(stamps))
    for row, i in zip(m.trajectory, order):
        np.testing.assert_allclose(row[1:4], poses[i][:3, 3], atol=1e-5)
        R = Rotation.from_quat(row[4:8]).as_matrix()
        np.testing.assert_allclose(R, poses[i][:3, :3], atol=1e-5)
        assert row[7] >= 0
    # the same map from its folder; the document is map.json's shape for the report
    assert load_map(tmp_path / "m").objects[0].label == "mouse"
    assert m.document["association"]["mode"] == "peer" and m.document["keyframes"] == 5
    assert len(m.document["objects"]) == 4


def test_oa_slam_s_layout_reads_the_same_map(tmp_path):
    """OA-SLAM: map objects with their track's id, labels from the tracks, keyframe times as
    seconds and nanoseconds: the same objects, labels and trajectory as GOReloc's layout."""
    rng = np.random.default_rng(5)
    objs = [(3, _random_ellipsoid(rng), {66: 4}), (8, _random_ellipsoid(rng), {41: 2})]
    kfs = [(1, 1311868164.363181, _pose(rng)), (2, 1311868165.5, _pose(rng))]
    a = load_map(write_osmap(tmp_path / "goreloc", objs, kfs))
    b = load_map(write_osmap(tmp_path / "oa", objs, kfs, oa_slam=True))
    assert [(o.id, o.label) for o in b.objects] == [(o.id, o.label) for o in a.objects] == [(3, "keyboard"), (8, "cup")]
    for x, y in zip(a.objects, b.objects):
        np.testing.assert_array_equal(x.ellipsoid.P, y.ellipsoid.P)
    np.testing.assert_allclose(b.trajectory, a.trajectory, rtol=0, atol=1e-6)
    (tmp_path / "oa" / "map.objecttracks").unlink()
    with pytest.raises(MapFormatError, match="the tracks file"):
        load_map(tmp_path / "oa")


def test_a_map_without_keyframes_has_no_trajectory(tmp_path):
    rng = np.random.default_rng(1)
    header = write_osmap(tmp_path, [(0, _random_ellipsoid(rng), {39: 1})])
    m = load_map(header)
    assert m.trajectory is None and any("no keyframes file" in n for n in m.notes)


def test_the_registry_finds_each_format_and_refuses_what_none_or_two_claim(tmp_path):
    assert list(MAP_FORMATS)[:2] == ["spdslam", "osmap"]
    run = tmp_path / "run"
    run.mkdir()
    e = Ellipsoid.from_axes(np.eye(3), np.zeros(3), np.array([0.1, 0.2, 0.3]))
    doc = map_document(method="multi-spd", parameterization="spd", iterations=1, final_cost=0.0,
                       initial_cost=0.0, converged=True, reason="", settings={}, objects=[MapObject(0, "cup", e)],
                       failed={}, notes=[], association={"mode": "auto"}, cost_by_factor={})
    write_map(run / "map.json", doc)
    for p in (run, run / "map.json"):
        m = load_map(p)
        assert m.is_spdslam and m.trajectory is None and m.objects[0].label == "cup"
    assert find_map_format(write_osmap(tmp_path / "o", [(0, e, {41: 1})])).name == "osmap"
    write_osmap(tmp_path / "o", [(0, e, {41: 1})], name="second")  # two headers: which one?
    with pytest.raises(MapFormatError, match="none of their layouts"):
        load_map(tmp_path / "o")
    with pytest.raises(MapFormatError, match="no such file or folder"):
        load_map(tmp_path / "nothing")
    with pytest.raises(ValueError, match="unknown map format"):
        load_map(run, format="nope")
    from spdslam.io import MapFormat

    with pytest.raises(TypeError, match="map format Untitled: title must be set"):
        type("Untitled", (MapFormat,), {"name": "untitled"})
    with pytest.raises(ValueError, match="a map format named 'osmap' is already registered"):
        type("Other", (MapFormat,), {"name": "osmap", "title": "t", "layout": "l"})
    assert list(MAP_FORMATS) == ["spdslam", "osmap"]


def _corpus(tmp_path: Path):
    """(name, header path, what the message must hold) of broken Osmap maps."""
    rng = np.random.default_rng(2)
    es = [_random_ellipsoid(rng) for _ in range(3)]
    objs = [(i, e, {41: 2}) for i, e in enumerate(es)]
    kfs = [(1, 1.0, _pose(rng)), (2, 2.0, _pose(rng))]
    cases = []

    def case(name, must, **kw):
        header = write_osmap(tmp_path / name, kw.pop("objects", objs), kw.pop("keyframes", kfs), **kw)
        cases.append((name, header, must))
        return header

    hyper = np.diag([1.0, -0.5, 0.3, -1.0]).reshape(-1).tolist()  # a hyperboloid
    case("hyperboloid", "dual quadric of an ellipsoid", quadrics={1: hyper})
    case("q33_zero", "Q*[3,3] ≠ 0", quadrics={0: np.diag([1.0, 1.0, 1.0, 0.0]).reshape(-1).tolist()})
    asym = _dual(es[0], -1.0)
    asym[0, 3] += 0.5
    case("asymmetric", "symmetric", quadrics={0: asym.reshape(-1).tolist()})
    case("nan", "16 finite numbers", quadrics={2: [float("nan")] * 16})
    case("short_quadric", "16 finite numbers", quadrics={2: [1.0] * 9})
    case("unknown_category", "COCO's 0–79", objects=[(0, es[0], {95: 4})])
    case("count_mismatch", "expected 5 objects", counts={"nObjects": 5})
    case("bad_count", "a count", counts={"nObjects": "many"})
    case("duplicate_id", "distinct object ids", objects=[(3, es[0], {41: 1}), (3, es[1], {41: 1})])
    case("no_times", "each keyframe's timestamp", keyframes=[(1, 0.0, kfs[0][2]), (2, 0.0, kfs[1][2])])
    h = case("missing_keyframes", "the keyframes file")
    (h.parent / "map.keyframes").unlink()
    h = case("truncated_objects", "map.objects")
    data = (h.parent / "map.objects").read_bytes()
    (h.parent / "map.objects").write_bytes(data[: len(data) // 2 + 3])
    h = case("truncated_keyframes", "map.keyframes")
    data = (h.parent / "map.keyframes").read_bytes()
    (h.parent / "map.keyframes").write_bytes(data[:-7])
    h = case("mismatched_histogram", "cat_ids and cat_counts")
    M = osmap_messages()
    oa = M["SerializedObjectArray"]()
    oa.ParseFromString((h.parent / "map.objects").read_bytes())
    oa.object[1].cat_counts.append(3)
    (h.parent / "map.objects").write_bytes(oa.SerializeToString())
    h = case("not_a_rotation", "rotation")
    ka = M["SerializedKeyframeArray"]()
    ka.ParseFromString((h.parent / "map.keyframes").read_bytes())
    ka.keyframe[0].pose.element[0] = 3.0
    (h.parent / "map.keyframes").write_bytes(ka.SerializeToString())
    h = case("short_pose", "12 finite numbers")
    ka = M["SerializedKeyframeArray"]()
    ka.ParseFromString((h.parent / "map.keyframes").read_bytes())
    del ka.keyframe[1].pose.element[11]
    (h.parent / "map.keyframes").write_bytes(ka.SerializeToString())
    h = case("header_line", "'key: value'")
    h.write_text(h.read_text() + "what is this\n")
    h = case("no_objects_file", "objects file")
    (h.parent / "map.objects").unlink()
    return cases


def test_every_broken_osmap_gives_one_line_naming_the_file(tmp_path):
    cases = _corpus(tmp_path)
    assert len(cases) >= 15
    for name, header, must in cases:
        with pytest.raises(MapFormatError) as info:
            load_map(header)
        msg = str(info.value)
        assert "\n" not in msg and str(header.parent) in msg and must in msg, (name, msg)


def test_random_truncations_and_byte_flips_are_refused_or_read(tmp_path):
    """Any cut of the objects binary is refused (a cut at a record's end leaves fewer objects
    than the header counts); a flipped byte is refused in one line or read into finite,
    valid objects: never another exception."""
    rng = np.random.default_rng(3)
    objs = [(i, _random_ellipsoid(rng), {41: 1 + i}) for i in range(6)]
    header = write_osmap(tmp_path / "ok", objs)
    data = (header.parent / "map.objects").read_bytes()
    r = random.Random(4)
    for cut in sorted(set(r.randrange(len(data)) for _ in range(40))):
        (header.parent / "map.objects").write_bytes(data[:cut])
        with pytest.raises(MapFormatError):
            load_map(header)
    read = 0
    for _ in range(60):
        b = bytearray(data)
        b[r.randrange(len(b))] ^= 1 << r.randrange(8)
        (header.parent / "map.objects").write_bytes(bytes(b))
        try:
            m = load_map(header)
        except MapFormatError as e:
            assert "\n" not in str(e)
            continue
        read += 1
        for o in m.objects:
            assert np.all(np.isfinite(o.ellipsoid.P)) and np.all(np.linalg.eigvalsh(o.ellipsoid.P) > 0)
            assert o.label in COCO80
    assert read < 60


# -- the command line --------------------------------------------------------------------------

#: the room's classes as COCO names (an Osmap's categories are COCO's)
_COCO_NAMES = {"sofa": "couch", "cabinet": "refrigerator", "table": "dining_table", "plant": "potted_plant"}


@pytest.fixture(scope="module")
def coco_room(tmp_path_factory):
    """(a synthetic room with COCO labels as a folder, an Osmap of its true objects and
    poses moved by G, G)."""
    base = tmp_path_factory.mktemp("osmap")
    seq = make_room_sequence(0, frames=40, objects=5, drift=0.0)
    rename = lambda s: _COCO_NAMES.get(s, s)  # noqa: E731
    seq = replace(seq, detections=[replace(d, label=rename(d.label)) for d in seq.detections],
                  objects_gt=[replace(g, label=rename(g.label)) for g in seq.objects_gt])
    write_sequence(seq, base / "room")
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("zyx", [40, 10, -5], degrees=True).as_matrix()
    G[:3, 3] = [1.5, -2.0, 0.3]
    objects = []
    for g in seq.objects_gt:
        c = g.cuboid
        e = Ellipsoid.from_axes(c.rotation, c.center, c.half_extents)
        objects.append((10 + g.id, transform_ellipsoid(e, G, 1.0), {COCO80.index(g.label): 12}))
    poses = moved_sequence(seq, G).poses_tum
    kfs = []
    for i in range(0, len(poses), 4):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(poses[i, 3:7]).as_matrix()
        T[:3, 3] = poses[i, :3]
        kfs.append((i, float(seq.timestamps[i]), T))
    header = write_osmap(base / "peer", objects, kfs)
    return base, header, G


def test_cli_evaluate_aligns_a_peer_map_by_its_keyframes(coco_room, tmp_path):
    base, header, G = coco_room
    before = sorted(p.name for p in header.parent.iterdir())
    assert_error(invoke("evaluate", header, base / "room"), "(osmap)", "--out")
    out = tmp_path / "ev"
    r = invoke("evaluate", header, base / "room", "--out", out)
    assert_ok(r)
    metrics = json.loads((out / "metrics.json").read_text())
    np.testing.assert_allclose(np.asarray(metrics["to_groundtruth"]) @ G, np.eye(4), atol=1e-4)
    s = metrics["summary"]
    assert s["matched"] == 5 and s["mean_iou"] > 0.99, s
    assert set(metrics["ate"]) == {"map"} and metrics["ate"]["map"]["rmse"] < 1e-4
    report = (out / "report.md").read_text()
    assert "A map read from" in report and "keyframes" in report and "ATE RMSE of the map's poses" in report
    assert sorted(p.name for p in header.parent.iterdir()) == before  # the peer map untouched


def test_cli_localize_against_a_peer_map(coco_room, tmp_path):
    base, header, G = coco_room
    out = tmp_path / "loc"
    r = invoke("localize", base / "room", "--map", header, "--out", out)
    assert_ok(r)
    T = np.asarray(json.loads((out / "localization.json").read_text())["T_map_sequence"])
    np.testing.assert_allclose(np.linalg.inv(G) @ T, np.eye(4), atol=0.02)


def test_cli_refuses_broken_peer_maps_in_one_line_and_writes_nothing(coco_room, tmp_path):
    base, _, _ = coco_room
    for name, header, must in _corpus(tmp_path / "corpus"):
        out = tmp_path / f"ev_{name}"
        assert_error(invoke("evaluate", header, base / "room", "--out", out), must)
        assert not out.exists(), name
    _, header, _ = coco_room
    assert_error(invoke("merge", header, header, "--out", tmp_path / "m"), "the map records no sequence",
                 "--sequence-a")
    assert_error(invoke("check", base / "room", "--map", header), "another system's map (osmap)",
                 "spdslam localize --map")
    bare = write_osmap(tmp_path / "bare", [(0, load_map(header).objects[0].ellipsoid, {41: 1})])  # no keyframes
    assert_error(invoke("merge", bare, header, "--sequence-a", base / "room", "--sequence-b", base / "room",
                        "--out", tmp_path / "m"), "--sequence-a", "has no keyframes")
    assert not (tmp_path / "m").exists()


def test_cli_merge_with_a_peer_map_is_in_its_frame(coco_room, tmp_path):
    """Another system's map (A) with the recording it was made from, merged with a run of
    spdslam (B, in the recording's own frame): one map in A's frame, an object seen in both one
    object."""
    base, header, G = coco_room
    run = tmp_path / "run"
    assert_ok(invoke("run", base / "room", "--out", run))
    out = tmp_path / "merged"
    assert_ok(invoke("merge", header, run, "--sequence-a", base / "room", "--out", out))
    doc = json.loads((out / "merge.json").read_text())
    assert doc["in_both"] >= 4 and doc["frames"] == {"a": 40, "b": 40}
    merged = load_map(out).objects
    peer = load_map(header).objects
    for o in merged:  # each merged object near the peer's of its label, in the peer's frame
        near = min(np.linalg.norm(np.asarray(o.ellipsoid.center) - np.asarray(p.ellipsoid.center))
                   for p in peer if p.label == o.label)
        assert near < 0.1, (o.label, near)
    assert all(len(o.observed_by) == 2 for o in merged if o.label != "object")


GORELOC = os.environ.get("SPDSLAM_GORELOC_MAP")


@pytest.mark.skipif(not GORELOC or not Path(GORELOC).exists(), reason="GOReloc's published map not given")
def test_goreloc_published_fr2_desk_map_reads():
    m = load_map(GORELOC)
    assert len(m.objects) == 47 and m.trajectory.shape == (198, 8)
    assert sum(o.label == "cup" for o in m.objects) == 8


def test_cli_view_of_a_peer_map_needs_its_out_and_writes_there(coco_room, tmp_path):
    pytest.importorskip("rerun")
    base, header, _ = coco_room
    before = sorted(p.name for p in header.parent.iterdir())
    assert_error(invoke("view", header), "(osmap)", "--out FILE")
    rec = tmp_path / "peer.rrd"
    assert_ok(invoke("view", header, "--sequence", base / "room", "--out", rec, "--no-images"))
    assert rec.stat().st_size > 0
    assert sorted(p.name for p in header.parent.iterdir()) == before
