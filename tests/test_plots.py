"""Figures (spdslam.experiments' plots, on spdslam.evaluation's ellipses): PNG files are written, and the geometry behind them
is right.

The geometry is checked against independent constructions: brute-force projected surface
points of the ellipsoid (top view and image), the point conic C = (C*)⁻¹ and the
closed-form box ``geometry.project_box``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from spdslam import Camera, Ellipsoid
from spdslam.evaluation import (
    camera_centers,
    conic_ellipse,
    conic_outline,
    plane_basis,
    top_view_ellipse,
)
from spdslam.experiments import plot_map_top, plot_overlay, write_overlays
from spdslam.geometry import Cuboid, conic_box, in_front, project_box, project_dual_quadric
from spdslam.geometry.se3 import from_tum, matrix_to_quat, to_matrix
from spdslam.io import Detection, GroundTruthObject, Sequence

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def assert_png(path, min_bytes: int = 2000) -> None:
    data = Path(path).read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > min_bytes


def png_size(path) -> tuple[int, int]:
    """(width, height) from the IHDR chunk."""
    data = Path(path).read_bytes()
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def tum_of(R, c) -> np.ndarray:
    return np.concatenate([c, matrix_to_quat(R)])


def scene():
    """A camera at the origin-ish looking along +y at two objects on the floor z = 0."""
    camera = Camera(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width=320, height=240)
    ells = [
        Ellipsoid.from_axes(rot_z(0.3), [0.0, 4.0, 0.5], [0.6, 0.4, 0.5]),
        Ellipsoid.from_axes(rot_z(-0.5), [1.2, 5.0, 0.4], [0.3, 0.3, 0.4]),
        Ellipsoid.from_axes(np.eye(3), [0.0, -4.0, 0.5], [0.3, 0.3, 0.3]),  # behind
    ]
    # Camera axes in the world: x right = +x, y down = −z, z forward = +y.
    R_wc = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    poses = np.array([tum_of(R_wc, [0.1 * k, 0.0, 0.6]) for k in range(4)])
    return camera, ells, poses


# --- geometry -------------------------------------------------------------------------------


def test_plane_basis_orthonormal_and_z_up_is_xy(rng):
    np.testing.assert_allclose(plane_basis((0, 0, 1)), [[1, 0, 0], [0, 1, 0]])
    for up in [(0, -1, 0), (1, 0, 0), rng.normal(size=3)]:
        B = plane_basis(up)
        np.testing.assert_allclose(B @ B.T, np.eye(2), atol=1e-12)
        u = np.asarray(up, float) / np.linalg.norm(up)
        np.testing.assert_allclose(B @ u, 0.0, atol=1e-12)
        assert np.cross(B[0], B[1]) @ u == pytest.approx(1.0)  # right-handed
    with pytest.raises(ValueError):
        plane_basis((0, 0, 0))


def test_top_view_ellipse_of_axis_aligned_and_yawed_ellipsoids():
    B = plane_basis((0, 0, 1))
    for yaw in (0.0, 0.7):
        P = np.asarray(Ellipsoid.from_axes(rot_z(yaw), [1.0, 2.0, 3.0], [3.0, 2.0, 1.0]).P)
        c, S = top_view_ellipse(P, [1.0, 2.0, 3.0], B)
        np.testing.assert_allclose(c, [1.0, 2.0])
        np.testing.assert_allclose(np.sqrt(np.linalg.eigvalsh(S)), [2.0, 3.0], rtol=1e-12)
        if yaw == 0.0:
            np.testing.assert_allclose(S, np.diag([9.0, 4.0]), atol=1e-12)


def test_top_view_ellipse_is_the_silhouette(gen):
    """Support function √(dᵀ S d) = max over surface points of d·(Bx − c), any direction d."""
    R, t, s = gen.ellipsoid_params()
    up = gen.rng.normal(size=3)
    B = plane_basis(up)
    c, S = top_view_ellipse(R @ np.diag(s**2) @ R.T, t, B)
    pts = gen.surface_points(R, t, s, 40000) @ B.T - c
    for a in np.linspace(0, np.pi, 7):
        d = np.array([np.cos(a), np.sin(a)])
        assert np.max(pts @ d) == pytest.approx(np.sqrt(d @ S @ d), rel=2e-3)


def test_projected_outline_lies_on_the_conic_and_spans_project_box(gen):
    cam = gen.camera()
    R, t, s = gen.ellipsoid_params()
    T, R_wc, c = gen.pose_looking_at(R, t, s)
    e = Ellipsoid.from_axes(R, t, s)
    assert bool(in_front(e, T))
    Cs = np.asarray(project_dual_quadric(e.dual_quadric(), T, cam))
    # The same from a TUM row (as the plots take poses) and from the camera's axes and centre.
    Cs7 = np.asarray(project_dual_quadric(e.dual_quadric(), from_tum(tum_of(R_wc, c)), cam))
    np.testing.assert_allclose(Cs7, Cs, rtol=1e-9, atol=1e-9 * np.abs(Cs).max())
    Csa = project_dual_quadric(np.asarray(e.dual_quadric()), (R_wc, c), cam)
    np.testing.assert_allclose(Csa, Cs, rtol=1e-9, atol=1e-9 * np.abs(Cs).max())

    uv = conic_outline(Cs, n=4000)
    assert uv.shape == (4001, 2)
    x = np.column_stack([uv, np.ones(len(uv))])
    C = np.linalg.inv(Cs)
    C = C / np.abs(np.linalg.eigvalsh(C)).max()
    xn = x / np.linalg.norm(x, axis=1, keepdims=True)
    assert np.abs(np.einsum("ni,ij,nj->n", xn, C, xn)).max() < 1e-9

    box = np.asarray(project_box(e, T, cam))
    size = np.max(box[2:] - box[:2])
    np.testing.assert_allclose(conic_box(Cs), box, atol=1e-9 * max(size, 1.0))
    sampled = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
    np.testing.assert_allclose(sampled, box, atol=1e-5 * size)

    # Independently: the silhouette of projected surface points fills the same box.
    Xc = gen.world_to_camera(gen.surface_points(R, t, s, 40000), R_wc, c)
    px = gen.pinhole(Xc, cam.fx, cam.fy, cam.cx, cam.cy)
    np.testing.assert_allclose(
        np.concatenate([px.min(0), px.max(0)]), box, atol=0.02 * size
    )


def test_conic_ellipse_sign_and_scale_invariant_and_rejects_non_ellipses():
    c0, S0 = np.array([3.0, -2.0]), np.array([[4.0, 1.0], [1.0, 2.0]])
    Cs = np.block([[S0 - np.outer(c0, c0), -c0[:, None]], [-c0[None, :], -np.ones((1, 1))]])
    for k in (1.0, -3.0, 1e-6):
        c, S = conic_ellipse(k * Cs)
        np.testing.assert_allclose(c, c0)
        np.testing.assert_allclose(S, S0, atol=1e-12)
    with pytest.raises(ValueError, match="not an ellipse"):
        conic_ellipse(np.diag([1.0, 1.0, 0.0]))
    with pytest.raises(ValueError, match="not an ellipse"):
        conic_ellipse(np.diag([1.0, -1.0, -1.0]))  # a hyperbola


def test_camera_centers_accepts_7_and_8_columns():
    rows7 = np.array([[1.0, 2.0, 3.0, 0, 0, 0, 1.0]])
    rows8 = np.column_stack([[10.0], rows7])
    np.testing.assert_array_equal(camera_centers(rows7), [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(camera_centers(rows8), [[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError):
        camera_centers(np.zeros((3, 6)))


# --- files ----------------------------------------------------------------------------------


def test_plot_map_top_writes_a_png(tmp_path):
    _, ells, poses = scene()
    gt = [
        GroundTruthObject(0, "box", Cuboid.from_yaw([0.0, 4.1, 0.5], 0.25, [0.55, 0.4, 0.5])),
        Cuboid.from_yaw([1.2, 5.0, 0.4], 0.0, [0.3, 0.3, 0.4]),
    ]
    gt_traj = np.column_stack([np.arange(len(poses)) * 0.1, poses + 0.01])
    out = plot_map_top(tmp_path / "top.png", ells, labels=["a", "b", "c"], gt_cuboids=gt,
                       trajectory=poses, gt_trajectory=gt_traj, title="map")  # fmt: skip
    assert out == tmp_path / "top.png"
    assert_png(out, 10000)
    # Other up directions and no optional inputs.
    assert_png(plot_map_top(tmp_path / "side.png", ells, up=(0, -1, 0)))
    assert_png(plot_map_top(tmp_path / "empty.png", []))
    with pytest.raises(ValueError, match="label"):
        plot_map_top(tmp_path / "bad.png", ells, labels=["a"])


def test_plot_overlay_without_image(tmp_path):
    camera, ells, poses = scene()
    boxes = [np.array([100.0, 60.0, 200.0, 150.0])]
    out = plot_overlay(tmp_path / "o.png", None, camera, poses[0], ells, boxes=boxes,
                       labels=["a", "b", "c"])  # fmt: skip
    assert_png(out)
    assert png_size(out) == (320, 240)


@pytest.mark.parametrize("suffix", ["png", "jpg"])
def test_plot_overlay_with_an_image_file(tmp_path, suffix):
    import matplotlib.image as mpimg

    camera, ells, poses = scene()
    yy, xx = np.mgrid[0:240, 0:320]
    img = np.stack([xx / 320, yy / 240, 0.5 * np.ones_like(xx, float)], axis=-1)
    img_path = tmp_path / f"frame.{suffix}"
    mpimg.imsave(img_path, img)
    T = to_matrix(from_tum(poses[1]))  # a 4×4 pose works too
    out = plot_overlay(tmp_path / "o.png", img_path, camera, T, ells)
    assert_png(out, 5000)
    assert png_size(out) == (320, 240)


def test_write_overlays_on_a_small_sequence(tmp_path):
    import matplotlib.image as mpimg

    camera, ells, poses = scene()
    stamps = np.array([0.0, 0.1, 0.2, 0.3])
    images = {}
    for t in (0.005, 0.105, 0.205):  # close to, not equal to, the poses'; none for frame 3
        p = tmp_path / "rgb" / f"{t:.6f}.png"
        p.parent.mkdir(exist_ok=True)
        mpimg.imsave(p, np.full((240, 320, 3), 0.4))
        images[t] = p
    dets = [
        Detection(0, 0.005, [110, 60, 210, 160], "chair", 0.9),
        Detection(0, 0.005, [220, 80, 260, 140], "box", 0.8),
        Detection(2, 0.205, [110, 60, 210, 160], "chair", 0.9),  # frame 1: no detections
        Detection(3, 0.305, [110, 60, 210, 160], "chair", 0.9),
    ]
    seq = Sequence("tiny", camera, stamps, poses, dets, images=images)
    out = write_overlays(tmp_path / "ov", seq, ells, poses)
    assert out == [tmp_path / "ov" / "0.005.png", tmp_path / "ov" / "0.205.png"]
    for p in out:
        assert_png(p)
    assert write_overlays(tmp_path / "ov1", seq, ells, poses, max_frames=1) == [
        tmp_path / "ov1" / "0.005.png"
    ]
    assert write_overlays(tmp_path / "ov2", seq, ells, poses, frames=[1, 2]) == [
        tmp_path / "ov2" / "0.205.png"
    ]
    # (N, 8) poses with timestamps are accepted; a wrong length is not.
    assert len(write_overlays(tmp_path / "ov3", seq, ells, np.column_stack([stamps, poses]))) == 2
    with pytest.raises(ValueError, match="poses_tum"):
        write_overlays(tmp_path / "ov4", seq, ells, poses[:2])
    # No images: nothing to do.
    bare = Sequence("bare", camera, stamps, poses, dets)
    assert write_overlays(tmp_path / "ov5", bare, ells, poses) == []
    assert not (tmp_path / "ov5").exists()


def test_conic_ellipses_batched_equal_one_at_a_time():
    """The batched conic → ellipse (used by the rerun recording) agrees with conic_ellipse
    where that one succeeds and flags exactly the conics it refuses."""
    from spdslam.evaluation import conic_ellipse, conic_ellipses, ellipse_points, ellipses_points

    rng = np.random.default_rng(3)
    A = rng.standard_normal((40, 2, 2))
    S0 = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(2)
    c0 = rng.uniform(-50, 50, (40, 2))
    C = np.zeros((40, 3, 3))  # real ellipses, at any non-zero scale and sign
    C[:, :2, :2] = S0 - c0[:, :, None] * c0[:, None, :]
    C[:, :2, 2] = C[:, 2, :2] = -c0
    C[:, 2, 2] = -1.0
    C *= rng.uniform(-3.0, 3.0, (40, 1, 1))
    C[:8] = rng.standard_normal((8, 3, 3))  # indefinite ones: hyperbolas or nothing
    C[8, 2, 2] = C[8, 2, 2] * 0.0
    C[9, 0, 0] = np.nan
    c, S, ok = conic_ellipses(C)
    pts = ellipses_points(c, S, 12)
    assert pts.shape == (40, 13, 2) and ok.sum() >= 20 and not ok[8] and not ok[9]
    for k in range(40):
        try:
            ck, Sk = conic_ellipse(C[k])
        except ValueError:
            assert not ok[k]
            continue
        assert ok[k]
        np.testing.assert_allclose(c[k], ck, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(S[k], Sk, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(pts[k], ellipse_points(ck, Sk, 12), rtol=1e-12, atol=1e-12)
