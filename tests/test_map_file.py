"""map.json as a versioned file (issue 49): the schema in docs/map.schema.json, version 1
maps read, newer ones refused, and the objects' covariance carried through a move."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from scipy.spatial.transform import Rotation

from spdslam.geometry import moved_covariance
from spdslam.io import MAP_VERSION, MapFormatError, read_map, write_sequence
from spdslam.synthetic import make_room_sequence

SCHEMA = Path(__file__).resolve().parents[1] / "docs" / "map.schema.json"


@pytest.fixture(scope="module")
def run_map(tmp_path_factory):
    base = tmp_path_factory.mktemp("mapfile")
    write_sequence(make_room_sequence(0, frames=30, objects=3), base / "room")
    assert_ok(invoke("run", base / "room", "--out", base / "run"))
    return base / "run" / "map.json"


def test_a_run_writes_a_map_the_schema_accepts(run_map):
    jsonschema = pytest.importorskip("jsonschema")
    doc = json.loads(run_map.read_text())
    schema = json.loads(SCHEMA.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(doc, schema)
    assert doc["version"] == MAP_VERSION == schema["properties"]["version"]["const"]
    for o in doc["objects"]:
        C = np.asarray(o["uncertainty"]["covariance"])
        assert C.shape == (9, 9) and np.allclose(C, C.T) and np.linalg.eigvalsh(C)[0] > -1e-12
        np.testing.assert_allclose(np.sqrt(np.diag(C)[:3]), o["uncertainty"]["center_sigma"], rtol=1e-9)
        assert o["observed_by"] == [{"recording": "room", "frames": o["observed_by"][0]["frames"]}]
    bad = dict(doc, version=3)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


def test_version_1_maps_are_read_and_newer_ones_refused(run_map, tmp_path):
    doc = json.loads(run_map.read_text())
    v1 = {k: v for k, v in doc.items() if k not in ("version", "units", "conventions")}
    v1["objects"] = [{k: v for k, v in o.items() if k != "observed_by"} for o in doc["objects"]]
    for o in v1["objects"]:
        o["uncertainty"] = {k: v for k, v in o["uncertainty"].items() if k != "covariance"}
    (tmp_path / "v1.json").write_text(json.dumps(v1))
    _, old = read_map(tmp_path / "v1.json")
    _, new = read_map(run_map)
    for a, b in zip(old, new):
        assert a.observed_by is None and b.observed_by is not None
        np.testing.assert_array_equal(a.ellipsoid.P, b.ellipsoid.P)
    for version, must in ((3, "a newer spdslam wrote it"), ("2", "version 1 to 2"), (0, "version 1 to 2")):
        (tmp_path / "v.json").write_text(json.dumps(dict(doc, version=version)))
        with pytest.raises(MapFormatError, match=must):
            read_map(tmp_path / "v.json")
    broken = dict(doc)
    broken["objects"] = [dict(doc["objects"][0], observed_by=[{"recording": 3, "frames": 1}])]
    (tmp_path / "b.json").write_text(json.dumps(broken))
    with pytest.raises(MapFormatError, match="observed_by"):
        read_map(tmp_path / "b.json")


def test_a_moved_covariance_is_the_move_s_jacobian_applied():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(9, 9))
    C = A @ A.T
    R, s = Rotation.random(random_state=rng).as_matrix(), 1.7
    iu = np.triu_indices(3)

    def move(x):  # (centre, P's xx xy xz yy yz zz) ↦ the same of x ↦ s R x + t
        P = np.zeros((3, 3))
        P[iu] = x[3:]
        P = P + np.triu(P, 1).T
        return np.r_[s * R @ x[:3] + 1.0, (s * s * R @ P @ R.T)[iu]]

    x0 = rng.normal(size=9)
    J = np.stack([(move(x0 + 1e-6 * e) - move(x0 - 1e-6 * e)) / 2e-6 for e in np.eye(9)], axis=1)
    np.testing.assert_allclose(moved_covariance(C, R, s), J @ C @ J.T, rtol=1e-7, atol=1e-7)
