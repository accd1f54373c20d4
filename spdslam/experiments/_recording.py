"""A run as a rerun recording (``.rrd``): the map, the trajectories and every frame's view.

Entity paths (world frame = the map's, i.e. the trajectory's frame):

- ``world``: view coordinates with the sequence's ``up`` (+z without priors), static;
- ``world/map/ellipsoids``: the mapped ellipsoids (``Ellipsoids3D``: centre, half-axes =
  radii, rotation; labels ``"<label> <id>"``), static;
- ``world/ground_truth/cuboids``: the ground-truth cuboids (``Boxes3D``), moved into the
  map's frame by ``to_groundtruth``⁻¹ when given; ``world/ground_truth/trajectory``;
- ``world/trajectory/optimized`` and ``world/trajectory/input``: camera centres
  (``LineStrips3D``), static;
- ``world/camera``: per frame, the pose T_wc (camera-to-world: ``Transform3D`` with the
  camera centre and R_wc), on the timelines ``frame`` (the sequence's frame index) and
  ``time`` (the TUM timestamp, seconds);
- ``world/camera/image``: the pinhole (``Pinhole``: K, the image size, RDF axes), static;
  under it, per frame: ``rgb`` (the image, when the sequence has one), ``detections``
  (``Boxes2D``) and ``ellipses`` (``LineStrips2D``: the outlines of the projected dual
  conics C* = M Q* Mᵀ of the mapped ellipsoids wholly in front of the camera). Without
  images the pinhole's resolution still sizes the 2D view like the camera image. Frames
  are the trajectory's rows: with keyframes, the kept frames only.

rerun-sdk (the ``viewer`` extra) is imported inside :func:`write_recording` only.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..evaluation import camera_centers, conic_ellipses, ellipses_points, ground_truth_in_map_frame
from ..geometry import (
    Ellipsoid,
    dual_quadric_of,
    in_front,
    project_dual_quadric,
    sorted_axes,
)
from ..geometry.se3 import matrix_to_quat, quat_to_matrix
from ..io import MATCH_TOLERANCE, nearest_stamps
from ._figures import image_for

__all__ = ["RERUN_MISSING", "projected_ellipses", "write_recording"]

#: The error when rerun-sdk is not installed.
RERUN_MISSING = "rerun-sdk is not installed: install the viewer extra, pip install 'spdslam[viewer]'"

#: tab10, as RGB bytes: one colour per mapped object (3D ellipsoid and 2D outline alike).
_PALETTE = np.array([(31, 119, 180), (255, 127, 14), (148, 103, 189), (140, 86, 75),
                     (227, 119, 194), (188, 189, 34), (23, 190, 207), (214, 39, 40),
                     (44, 160, 44), (127, 127, 127)], dtype=np.uint8)  # fmt: skip
_DETECTION_COLOR = (0, 230, 0)
#: Frames projected at once (bounds the memory of the outlines: block × objects × points).
_BLOCK = 256
_GT_COLOR = (40, 40, 40)


def _import_rerun():
    try:
        import rerun as rr
        import rerun.blueprint as rrb
    except ImportError:
        raise ImportError(RERUN_MISSING) from None
    return rr, rrb


def _tum_rows(traj, name: str) -> np.ndarray:
    """(N, 8) ``timestamp tx ty tz qx qy qz qw``; (N, 7) rows get the row index as stamp."""
    a = np.asarray(traj, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (7, 8):
        raise ValueError(f"{name}: expected TUM rows of shape (N, 7) or (N, 8), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values")
    if a.shape[1] == 7:
        a = np.column_stack([np.arange(len(a), dtype=float), a])
    return a


def _frames_of(stamps: np.ndarray, seq_stamps: np.ndarray) -> np.ndarray:
    """The sequence frame index of each stamp (nearest, within ``MATCH_TOLERANCE``), else
    ValueError (a trajectory of another sequence)."""
    if seq_stamps.size == 0:
        raise ValueError("the sequence has no frames")
    order = np.argsort(seq_stamps)
    nearest, ok = nearest_stamps(seq_stamps[order], stamps)
    if not ok.all():
        raise ValueError(
            f"trajectory timestamp {stamps[np.flatnonzero(~ok)[0]]!r} is not a frame of the "
            f"sequence (none within {MATCH_TOLERANCE} s): expected the sequence the run was "
            "made from"
        )
    return order[nearest]


def projected_ellipses(P, t, R_wc, c, camera, n_points: int = 64):
    """Outlines of the ellipsoids (P (N, 3, 3), t (N, 3)) seen by F cameras (R_wc (F, 3, 3),
    c (F, 3); T_wc camera-to-world), all at once: (points (F, N, n+1, 2), ok (F, N)).

    C* = M Q* Mᵀ (``geometry.project_dual_quadric``); its ellipse (c, S) and outline
    c + S^½ (cos θ, sin θ), closed, as ``conic_ellipses`` and ``ellipses_points``. ``ok``
    is False where the ellipsoid is not wholly in front of the camera (``geometry.in_front``)
    or C* is not a real ellipse; those outlines are meaningless.
    """
    P = np.asarray(P, dtype=float).reshape(-1, 3, 3)
    t = np.asarray(t, dtype=float).reshape(-1, 3)
    pose = (np.asarray(R_wc, dtype=float)[:, None], np.asarray(c, dtype=float)[:, None])
    C = project_dual_quadric(dual_quadric_of(P, t), pose, camera)  # (F, N, 3, 3)
    centre, S, ok = conic_ellipses(C)
    ok &= np.asarray(in_front(Ellipsoid(P, t), pose))
    return ellipses_points(centre, S, n_points), ok


def _world_axes(rr, up):
    """The ``world`` view coordinates for an axis-aligned ``up``, else None."""
    u = np.asarray(up, dtype=float).reshape(3)
    u = u / np.linalg.norm(u)
    k = int(np.argmax(np.abs(u)))
    if abs(u[k]) < 0.999:
        return None
    name = f"RIGHT_HAND_{'XYZ'[k]}_{'UP' if u[k] > 0 else 'DOWN'}"
    return getattr(rr.ViewCoordinates, name)


def write_recording(path, objects, trajectory, sequence=None, input_trajectory=None, *,
                    to_groundtruth=None, camera=None, images: bool = True, n_points: int = 64,
                    application_id: str = "spdslam") -> Path:  # fmt: skip
    """Write a rerun recording of a run to ``path`` (``.rrd``, atomically); returns ``Path(path)``.

    ``objects``: the mapped objects (``id``, ``label``, ``ellipsoid``: ``io.MapObject``s, or
    bare landmarks with ``P`` and ``center``). ``trajectory``: the optimised poses T_wc
    (camera-to-world) as TUM rows (N, 8) ``timestamp tx ty tz qx qy qz qw`` (or (N, 7):
    the row index is the stamp); one frame of the timeline per row. ``sequence``: the
    ``io.Sequence`` the run was made from, or None; it gives the camera, the detections,
    the images, the ground truth and the default ``input_trajectory`` (its own poses).
    ``to_groundtruth``: the 4×4 motion from the map's frame to the ground truth's (map.json's
    ``to_groundtruth``); the ground truth is drawn moved by its inverse. ``camera``: the
    intrinsics (default the sequence's); without any, no pinhole nor 2D view is logged.
    ``images``: log the sequence's images. Entity paths: the module docstring.

    Raises ``ImportError`` (``RERUN_MISSING``) without rerun-sdk and ``ValueError`` for a
    trajectory whose stamps are not the sequence's frames.
    """
    rr, rrb = _import_rerun()
    path = Path(path)
    traj = _tum_rows(trajectory, "trajectory")
    if input_trajectory is None and sequence is not None:
        input_trajectory = np.column_stack([sequence.timestamps, sequence.poses_tum])
    inp = None if input_trajectory is None else _tum_rows(input_trajectory, "input_trajectory")
    camera = camera if camera is not None else getattr(sequence, "camera", None)
    T = None if to_groundtruth is None else np.asarray(to_groundtruth, dtype=float)
    if T is not None and (T.shape != (4, 4) or not np.all(np.isfinite(T))):
        raise ValueError(f"to_groundtruth: expected a finite 4×4 matrix, got shape {T.shape}")
    frames = (np.arange(len(traj)) if sequence is None
              else _frames_of(traj[:, 0], np.asarray(sequence.timestamps, dtype=float)))

    # the map, as NumPy: P, t, sorted axes, labels, colours
    objects = list(objects)
    ells = [getattr(o, "ellipsoid", o) for o in objects]
    P = np.array([np.asarray(e.P, dtype=float) for e in ells]).reshape(-1, 3, 3)
    t = np.array([np.asarray(e.center, dtype=float) for e in ells]).reshape(-1, 3)
    labels = [f"{getattr(o, 'label', 'object')} {getattr(o, 'id', i)}" for i, o in enumerate(objects)]
    colors = _PALETTE[np.arange(len(objects)) % len(_PALETTE)]
    R_wc = quat_to_matrix(traj[:, 4:8]).reshape(-1, 3, 3)
    centres = traj[:, 1:4]

    def outlines_of(rows: slice):
        """(F, N, n+1, 2) outlines of the frames ``rows`` and (F, N) which to draw: real
        ellipses that meet the image."""
        pts, ok = projected_ellipses(P, t, R_wc[rows], centres[rows], camera, n_points)
        lo, hi = pts.min(axis=-2), pts.max(axis=-2)
        ok &= np.all(hi > -0.5, axis=-1) & (lo[..., 0] < camera.width - 0.5) & (lo[..., 1] < camera.height - 0.5)
        return pts, ok

    by_frame: dict[int, list] = {}
    for d in getattr(sequence, "detections", None) or []:
        by_frame.setdefault(d.frame, []).append(d)

    blueprint = rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="map"),
        *([rrb.Spatial2DView(origin="world/camera/image", name="camera")] if camera is not None else []),
    ))  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    rec = rr.RecordingStream(application_id)
    try:
        rec.save(tmp, default_blueprint=blueprint)
        up = (0.0, 0.0, 1.0)
        priors = getattr(sequence, "priors", None)
        if priors is not None and priors.up is not None:
            up = priors.up
        axes = _world_axes(rr, up)
        if axes is not None:
            rec.log("world", axes, static=True)
        if len(objects):
            R, s = (np.asarray(a) for a in sorted_axes(P))
            rec.log("world/map/ellipsoids", rr.Ellipsoids3D(
                centers=t, half_sizes=np.maximum(s, 1e-9), quaternions=matrix_to_quat(R),
                labels=labels, colors=colors), static=True)  # fmt: skip
        if sequence is not None and (sequence.objects_gt or sequence.groundtruth_tum is not None):
            cuboids, gt_traj = ground_truth_in_map_frame(sequence, T)
            if cuboids:
                rec.log("world/ground_truth/cuboids", rr.Boxes3D(
                    centers=[c.center for c in cuboids], half_sizes=[c.half_extents for c in cuboids],
                    quaternions=matrix_to_quat(np.array([c.rotation for c in cuboids])),
                    labels=[f"{g.label} {g.id}" for g in sequence.objects_gt],
                    colors=_GT_COLOR), static=True)  # fmt: skip
            if gt_traj is not None and len(gt_traj):
                rec.log("world/ground_truth/trajectory",
                        rr.LineStrips3D([camera_centers(gt_traj)], colors=(120, 120, 120)), static=True)
        rec.log("world/trajectory/optimized",
                rr.LineStrips3D([centres], colors=(214, 39, 40), labels=["optimised"]), static=True)
        if inp is not None:
            rec.log("world/trajectory/input",
                    rr.LineStrips3D([camera_centers(inp)], colors=(31, 119, 180), labels=["input"]), static=True)
        if camera is not None:
            extent = float(np.ptp(centres, axis=0).max()) if len(centres) else 1.0
            rec.log("world/camera/image", rr.Pinhole(
                image_from_camera=np.asarray(camera.K, dtype=float),
                resolution=[float(camera.width), float(camera.height)],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=float(np.clip(0.05 * extent, 0.05, 0.5))), static=True)  # fmt: skip
        q_wc = matrix_to_quat(R_wc)
        for r, f in enumerate(frames):
            f = int(f)
            rec.set_time("frame", sequence=f)
            rec.set_time("time", duration=float(traj[r, 0]))
            rec.log("world/camera", rr.Transform3D(  # T_wc: camera (child) -> world (parent)
                translation=centres[r], quaternion=rr.Quaternion(xyzw=q_wc[r]),
                relation=rr.TransformRelation.ParentFromChild))  # fmt: skip
            if camera is None:
                continue
            dets = by_frame.get(f, [])
            boxes = np.array([d.box for d in dets], dtype=float).reshape(-1, 4)
            rec.log("world/camera/image/detections", rr.Boxes2D(
                array=boxes, array_format=rr.Box2DFormat.XYXY, colors=_DETECTION_COLOR,
                labels=[d.label if d.instance is None else f"{d.label} {d.instance}" for d in dets]))  # fmt: skip
            if r % _BLOCK == 0 and len(objects):  # projected a block of frames at a time
                outlines, ok = outlines_of(slice(r, r + _BLOCK))
            keep = np.flatnonzero(ok[r % _BLOCK]) if len(objects) else np.zeros(0, dtype=int)
            rec.log("world/camera/image/ellipses", rr.LineStrips2D(
                [outlines[r % _BLOCK, k] for k in keep], colors=colors[keep],
                labels=[labels[k] for k in keep]))  # fmt: skip
            if images and sequence is not None and sequence.images:
                found = image_for(sequence, f, dets, MATCH_TOLERANCE + 1e-9)
                if found is not None and Path(found[1]).is_file():
                    rec.log("world/camera/image/rgb", _image(rr, Path(found[1])))
                else:
                    rec.log("world/camera/image/rgb", rr.Clear(recursive=False))
        rec.flush()
        rec.disconnect()
        os.replace(tmp, path)
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    return path


def _image(rr, path: Path):
    """PNG and JPEG files as they are (``EncodedImage``); other formats decoded."""
    if path.suffix.lower() in (".png", ".jpg", ".jpeg"):
        return rr.EncodedImage(path=path)
    import matplotlib.image as mpimg

    return rr.Image(mpimg.imread(str(path)))
