"""Maps exported for other tools (issue 49): a Spark-DSG scene graph that ``spark_dsg`` loads
back, and a glTF scene that ``trimesh`` loads with a mesh per object on its ellipsoid."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_cli_error as assert_error
from conftest import assert_cli_ok as assert_ok
from conftest import cli_invoke as invoke
from scipy.spatial.transform import Rotation
from test_osmap import write_osmap

from spdslam import Ellipsoid
from spdslam.io import MapObject, SavedMap, export_map, load_map, map_document, write_map


def _objects():
    rng = np.random.default_rng(0)
    out = []
    specs = (("cup", (0.04, 0.05, 0.06)), ("sofa", (1.0, 0.45, 0.4)), ("book", (0.1, 0.08, 0.02)))
    for i, (label, r) in enumerate(specs):
        e = Ellipsoid.from_axes(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-2, 2, 3), np.array(r))
        C = np.diag(np.arange(1.0, 10.0)) * 1e-4
        u = {"center_sigma": [0.01] * 3, "center_sigma_max": 0.01, "log_radius_sigma": [0.1] * 3,
             "covariance": C.tolist()}
        out.append(MapObject(10 + i, label, e, u, (("day1", 40 + i), ("day2", 3))))
    return out


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """A map folder: map.json (three objects) and a trajectory."""
    base = tmp_path_factory.mktemp("export") / "run"
    base.mkdir()
    doc = map_document(method="multi-spd", parameterization="spd", iterations=3, final_cost=1.0, initial_cost=2.0,
                       converged=True, reason="", settings={}, objects=_objects(), failed={}, notes=[],
                       association={"mode": "auto"}, cost_by_factor={})
    write_map(base / "map.json", doc)
    t = np.linspace(0, 2, 20)
    rows = np.c_[t, np.cos(t), np.sin(t), 0.2 * t, np.zeros((20, 3)), np.ones(20)]
    np.savetxt(base / "trajectory.txt", rows)
    return base


@pytest.mark.parametrize("name", ["map.glb", "map.gltf"])
def test_gltf_has_a_mesh_per_object_on_its_ellipsoid(run_folder, tmp_path, name):
    trimesh = pytest.importorskip("trimesh")
    saved = load_map(run_folder)
    path = export_map(saved, "gltf", tmp_path / name)
    scene = trimesh.load(path)
    assert set(scene.geometry) == {f"{o.label} {o.id}" for o in saved.objects} | {"trajectory"}
    for o in saved.objects:
        mesh = scene.geometry[f"{o.label} {o.id}"]
        assert mesh.is_watertight and len(mesh.faces) > 500
        P, t = np.asarray(o.ellipsoid.P), np.asarray(o.ellipsoid.center)
        d = mesh.vertices - t
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", d, np.linalg.inv(P), d), 1.0, atol=1e-5)
        n = mesh.vertex_normals
        g = d @ np.linalg.inv(P)
        np.testing.assert_allclose(n, g / np.linalg.norm(g, axis=1, keepdims=True), atol=1e-4)
        np.testing.assert_allclose(mesh.volume, 4 / 3 * np.pi * np.prod(o.ellipsoid.axes()[1]), rtol=0.03)


def test_gltf_up_turns_the_map_s_up_to_y(run_folder, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    saved = load_map(run_folder)
    a = trimesh.load(export_map(saved, "gltf", tmp_path / "a.glb"))
    b = trimesh.load(export_map(saved, "gltf", tmp_path / "b.glb", up=[0.0, 0.0, 1.0]))
    for k in a.geometry:
        va, vb = a.geometry[k].vertices, b.geometry[k].vertices
        np.testing.assert_allclose(vb[:, 1], va[:, 2], atol=1e-5)  # z became y
        np.testing.assert_allclose(np.linalg.norm(vb, axis=1), np.linalg.norm(va, axis=1), atol=1e-5)


@pytest.mark.parametrize("name", ["map.json", "map.sparkdsg"])
def test_spark_dsg_loads_back_with_every_object(run_folder, tmp_path, name):
    dsg = pytest.importorskip("spark_dsg")
    saved = load_map(run_folder)
    path = export_map(saved, "spark-dsg", tmp_path / name)
    G = dsg.DynamicSceneGraph.load(str(path))
    layer = G.get_layer(dsg.DsgLayers.OBJECTS)
    assert layer.num_nodes() == len(saved.objects) == G.num_nodes()
    names = G.get_labelspace("OBJECTS").labels_to_names
    for o in saved.objects:
        a = G.get_node(dsg.NodeSymbol("O", o.id)).attributes
        R, r = (np.asarray(x) for x in o.ellipsoid.axes())
        np.testing.assert_allclose(a.position, o.ellipsoid.center, atol=1e-9)
        np.testing.assert_allclose(a.bounding_box.dimensions, 2 * r, rtol=1e-6)
        np.testing.assert_allclose(a.bounding_box.world_P_center, o.ellipsoid.center, atol=1e-6)
        Rb = np.asarray(a.bounding_box.world_R_center)
        np.testing.assert_allclose(np.abs(Rb.T @ R), np.eye(3), atol=1e-5)  # the same axes, up to sign
        assert a.name == f"{o.label} {o.id}" and names[a.semantic_label] == o.label
        meta = a.metadata.get()["spdslam"]
        np.testing.assert_allclose(meta["uncertainty"]["covariance"], o.uncertainty["covariance"])
        assert [(e["recording"], e["frames"]) for e in meta["observed_by"]] == list(o.observed_by)
    assert names[41] == "cup" and names[1000] == "sofa"  # COCO's index; others from 1000


def test_cli_export_writes_each_format_and_refuses_in_one_line(run_folder, tmp_path):
    out = tmp_path / "scene.glb"
    r = invoke("export", run_folder, "--format", "gltf", "--out", out)
    assert_ok(r)
    assert out.stat().st_size > 0 and "3 objects" in " ".join(r.output.split())
    assert_error(invoke("export", run_folder, "--format", "gltf", "--out", out), "exists", "--overwrite")
    assert_ok(invoke("export", run_folder, "--format", "gltf", "--out", out, "--overwrite", "--up", "0,0,1"))
    for args, must in ((("--format", "ply", "--out", tmp_path / "a.ply"), "spark-dsg, gltf"),
                       (("--format", "gltf", "--out", tmp_path / "a.obj"), ".glb or .gltf"),
                       (("--format", "spark-dsg", "--out", tmp_path / "a.json", "--up", "0,0,1"), "glTF scene only"),
                       (("--format", "gltf", "--out", tmp_path / "a.glb", "--up", "0,0"), "three numbers"),
                       (("--format", "gltf", "--out", tmp_path / "dir.glb"), "a folder")):
        (tmp_path / "dir.glb").mkdir(exist_ok=True)
        assert_error(invoke("export", run_folder, *args), must)
    assert_error(invoke("export", tmp_path / "nothing", "--format", "gltf", "--out", tmp_path / "b.glb"),
                 "no such file or folder")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "map.json").write_text(json.dumps({"version": 9}))
    assert_error(invoke("export", broken, "--format", "gltf", "--out", tmp_path / "c.glb"), "newer spdslam")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "dir.glb", "scene.glb"]


def test_another_system_s_map_exports_too(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    e = Ellipsoid.from_axes(np.eye(3), np.array([1.0, 2.0, 0.5]), np.array([0.3, 0.2, 0.1]))
    header = write_osmap(tmp_path / "peer", [(4, e, {41: 3})])
    saved = load_map(header)
    scene = trimesh.load(export_map(saved, "gltf", tmp_path / "peer.glb"))
    assert list(scene.geometry) == ["cup 4"]
    assert isinstance(saved, SavedMap) and saved.trajectory is None
