"""Figures of a map and of its projection into the images (PNG, matplotlib's Agg canvas).

- ``plot_map_top``: a top view, the orthographic projection along ``up``. With B the 2×3
  matrix whose rows are an orthonormal basis of the plane ⟂ up, the ellipsoid
  {t + L u : ‖u‖ ≤ 1} (P = L Lᵀ) projects to {B t + B L u}, the ellipse with centre B t and
  2×2 shape B P Bᵀ (``top_view_ellipse``). A cuboid's footprint is the convex hull of its
  8 projected corners.
- ``plot_overlay``: an image with each landmark's projected outline. The dual conic
  C* = M Q* Mᵀ (M = K [R_cw | t_cw]), scaled to C*₃₃ = −1, is [[S − ccᵀ, −c], [−cᵀ, −1]]
  for the ellipse {x : (x − c)ᵀ S⁻¹ (x − c) ≤ 1} whose point conic is C ∝ (C*)⁻¹
  (``conic_ellipse``); the outline is c + S^½ (cos θ, sin θ) (``conic_outline``) and its
  bounding box c ± √diag S is ``geometry.project_box``.
- ``write_overlays``: one overlay per frame of a ``Sequence`` with an image and detections.

matplotlib is imported inside the functions (``matplotlib.figure.Figure``, which renders
with Agg and does not touch pyplot's global state), never when spdslam is imported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation import (
    camera_centers,
    conic_ellipse,
    ellipse_points,
    plane_basis,
    top_view_ellipse,
)
from ..geometry import Ellipsoid, in_front, project_dual_quadric
from ..geometry.se3 import as_pose, from_tum
from ..io import MATCH_TOLERANCE

__all__ = [
    "LATENCY_COLUMNS",
    "image_for",
    "latency_csv",
    "plot_latency",
    "plot_map_top",
    "plot_overlay",
    "write_overlays",
]

_COLORS = ("tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink",
           "tab:olive", "tab:cyan", "tab:red", "tab:green", "tab:gray")  # fmt: skip


def _pose(T_wc):
    """jaxlie.SE3 from an SE3, a 4×4 matrix or TUM ``tx ty tz qx qy qz qw`` (7,)."""
    if isinstance(T_wc, (np.ndarray, list, tuple)) and np.shape(T_wc) == (7,):
        v = np.asarray(T_wc, dtype=float)
        if not np.all(np.isfinite(v)):
            raise ValueError("pose has non-finite entries")
        return from_tum(v)
    return as_pose(T_wc)


def _landmark(e) -> tuple[np.ndarray, np.ndarray]:
    """(P, t) as numpy from an object with ``.P`` and ``.center`` (any spdslam landmark)."""
    return np.asarray(e.P, dtype=float), np.asarray(e.center, dtype=float)


def _figure(**kw):
    from matplotlib.figure import Figure

    return Figure(**kw)


def _save(fig, path, dpi) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=dpi, format="png")
    return path


# --- top view -------------------------------------------------------------------------------


def _axis_name(e: np.ndarray) -> str:
    for k, name in enumerate("xyz"):
        if abs(abs(e[k]) - 1.0) < 1e-12:
            return ("−" if e[k] < 0 else "") + name
    return "(" + ", ".join(f"{x:.2f}" for x in e) + ")"


def _place_labels(fig, ax, anchors, texts, colors, fontsize: float = 7.0) -> None:
    """Labels at ``anchors`` (data coordinates) that do not cover each other: each is put
    at its anchor if that is free, else at the first free point of rings of growing
    radius around it (joined to the anchor by a thin line), largest objects first."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    renderer = FigureCanvasAgg(fig).get_renderer()
    ax.apply_aspect()
    frame = ax.get_window_extent(renderer)
    rings = [(0.0, 0.0)] + [(r * np.cos(a), r * np.sin(a)) for r in (11, 22, 34, 48, 64)
                            for a in np.linspace(0, 2 * np.pi, 12, endpoint=False) + r]
    placed: list = []
    for xy, text, color in zip(anchors, texts, colors):
        for k, (dx, dy) in enumerate(rings):
            t = ax.annotate(
                text, xy, xytext=(dx, dy), textcoords="offset points", ha="center",
                va="center", fontsize=fontsize, color=color,
                arrowprops=None if k == 0 else dict(arrowstyle="-", color=color, lw=0.6),
            )
            t.update_positions(renderer)
            bb = Text.get_window_extent(t, renderer).expanded(1.08, 1.15)
            free = all(not bb.overlaps(o) for o in placed)
            inside = frame.contains(bb.x0, bb.y0) and frame.contains(bb.x1, bb.y1)
            if (free and inside) or k == len(rings) - 1:
                placed.append(bb)
                break
            t.remove()


def _draw_map(ax, B, ellipsoids, gt_cuboids, trajectories, legend: bool, loops=()):
    """Ellipsoids, ground-truth footprints, trajectories and loop closures (``plot_map_top``)
    of a top view on ``ax``; returns each ellipsoid's (centre, colour, area)."""
    from matplotlib.collections import PolyCollection
    from scipy.spatial import ConvexHull, QhullError

    out, fills = [], []
    for i, e in enumerate(ellipsoids):
        P, t = _landmark(e)
        c, S = top_view_ellipse(P, t, B)
        xy = ellipse_points(c, S, 120)
        color = _COLORS[i % len(_COLORS)]
        fills.append(xy)
        ax.plot(xy[:, 0], xy[:, 1], "-", color=color, lw=1.2,
                label="estimated ellipsoids" if i == 0 and legend else None)  # fmt: skip
        out.append((c, color, float(np.sqrt(max(np.linalg.det(S), 0.0)))))
    if fills:  # the outlines above set the data limits; one collection fills them all
        ax.add_collection(PolyCollection(fills, facecolors=[color for _, color, _ in out], alpha=0.15,
                                         linewidths=0), autolim=False)
    for i, g in enumerate(gt_cuboids or []):
        cub = getattr(g, "cuboid", g)
        pts = np.asarray(cub.corners(), dtype=float) @ B.T
        try:
            hull = pts[ConvexHull(pts).vertices]
        except QhullError:  # a footprint of zero area (a cuboid seen edge-on cannot be)
            hull = pts
        hull = np.vstack([hull, hull[:1]])
        ax.plot(hull[:, 0], hull[:, 1], "--", color="black", lw=1.0,
                label="ground-truth cuboids" if i == 0 and legend else None)  # fmt: skip
    for traj, style, color, name in trajectories:
        if traj is None:
            continue
        xy = camera_centers(traj) @ B.T
        if len(xy) == 0:
            continue
        ax.plot(xy[:, 0], xy[:, 1], style, color=color, lw=1.0, label=name if legend else None)
        ax.plot(xy[:1, 0], xy[:1, 1], "o", color=color, ms=4)
    est = trajectories[-1][0] if trajectories else None
    if loops and est is not None and len(est):
        xy = camera_centers(est) @ B.T
        shown: set = set()
        for a, b, closed in loops:
            if not (0 <= a < len(xy) and 0 <= b < len(xy)):
                continue
            name = "loop closed" if closed else "loop rejected"
            ax.plot(xy[[a, b], 0], xy[[a, b], 1], "-" if closed else ":", color="tab:green" if closed else "tab:purple",
                    lw=1.8 if closed else 1.0, label=name if legend and name not in shown else None)
            shown.add(name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(f"{_axis_name(B[0])} [m]")
    ax.set_ylabel(f"{_axis_name(B[1])} [m]")
    ax.grid(alpha=0.3)
    return out


#: Above this many objects, or when the trajectory spans more than ``ZOOM_RATIO`` times
#: the objects' extent, the top view adds a zoomed panel on the objects.
ZOOM_OBJECTS = 12
ZOOM_RATIO = 2.5


def plot_map_top(path, ellipsoids, labels=None, gt_cuboids=None, trajectory=None,
                 gt_trajectory=None, up=(0.0, 0.0, 1.0), title=None, dpi: int = 110, loops=()) -> Path:  # fmt: skip
    """Top view of a map, saved as PNG at ``path``; returns ``Path(path)``.

    ``ellipsoids``: landmarks (``.P`` and ``.center``), drawn as their silhouettes
    (``top_view_ellipse``) with ``labels`` (default: their indices) placed so that they do
    not cover each other; ``gt_cuboids``: ``Cuboid``s or objects with ``.cuboid`` (e.g.
    ``GroundTruthObject``), drawn dashed as footprints; ``trajectory`` / ``gt_trajectory``:
    TUM rows (N, 7) or (N, 8) of the estimated and ground-truth camera poses; ``loops``:
    (frame a, frame b, closed) of the loop closures tried, each drawn between the two
    estimated camera centres (closed: solid green; rejected in the pose graph: dotted). ``up``
    is the viewing direction (the plot's axes are ``plane_basis(up)``). With many objects, or a
    trajectory much larger than the objects' extent, a second panel zooms on the objects
    (the labels go there).
    """
    B = plane_basis(up)
    ellipsoids = list(ellipsoids)
    if labels is not None and len(labels) != len(ellipsoids):
        raise ValueError(f"need one label per ellipsoid, got {len(labels)} for {len(ellipsoids)}")
    texts = [str(i) if labels is None else str(labels[i]) for i in range(len(ellipsoids))]
    trajectories = ((gt_trajectory, "--", "0.45", "ground-truth trajectory"),
                    (trajectory, "-", "tab:red", "estimated trajectory"))
    centres = np.array([top_view_ellipse(*_landmark(e), B)[0] for e in ellipsoids]).reshape(-1, 2)
    zoom = False
    if len(centres):
        extent = np.ptp(centres, axis=0).max() + 0.5
        span = max([np.ptp(camera_centers(t) @ B.T, axis=0).max()
                    for t, *_ in trajectories if t is not None and len(t)] or [0.0])
        zoom = len(ellipsoids) > ZOOM_OBJECTS or span > ZOOM_RATIO * extent
    fig = _figure(figsize=(13.0, 6.2) if zoom else (7.0, 6.0))
    ax = fig.add_subplot(1, 2, 1) if zoom else fig.add_subplot()
    drawn = _draw_map(ax, B, ellipsoids, gt_cuboids, trajectories, legend=True, loops=loops)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8, loc="best")
    name = title if title is not None else f"top view (up = {_axis_name(np.cross(B[0], B[1]))})"
    ax.set_title(name)
    target = ax
    if zoom:
        target = fig.add_subplot(1, 2, 2)
        drawn = _draw_map(target, B, ellipsoids, gt_cuboids, (), legend=False)
        outline = np.concatenate([ellipse_points(*top_view_ellipse(*_landmark(e), B), 60)
                                  for e in ellipsoids])
        lo, hi = outline.min(axis=0) - 0.1, outline.max(axis=0) + 0.1
        target.set_aspect("equal", adjustable="box")
        target.set_xlim(lo[0], hi[0])
        target.set_ylim(lo[1], hi[1])
        target.set_title(f"objects ({len(ellipsoids)})")
    fig.tight_layout()
    order = sorted(range(len(drawn)), key=lambda i: -drawn[i][2])
    _place_labels(fig, target, [drawn[i][0] for i in order], [texts[i] for i in order],
                  [drawn[i][1] for i in order])
    return _save(fig, path, dpi)


# --- image overlays -------------------------------------------------------------------------


def _read_image(image):
    if image is None:
        return None
    if isinstance(image, np.ndarray):
        return image
    import matplotlib.image as mpimg

    return mpimg.imread(str(image))  # PNG natively, JPEG and others through Pillow


def _box_of(b):
    """(box (4,), label or None) of a box array or an object with ``.box`` (a Detection)."""
    if hasattr(b, "box"):
        return np.asarray(b.box, dtype=float), getattr(b, "label", None)
    return np.asarray(b, dtype=float).reshape(4), None


def plot_overlay(path, image, camera, T_wc, ellipsoids, boxes=None, labels=None,
                 dpi: int = 100, n_points: int = 100) -> Path:  # fmt: skip
    """One view saved as PNG at ``path`` (``camera.width`` × ``camera.height`` pixels at the
    given dpi); returns ``Path(path)``.

    ``image``: a file (``matplotlib.image.imread``), an array, or None for a blank canvas;
    it is stretched to the camera's size. ``T_wc``: camera-to-world pose (jaxlie.SE3, 4×4
    or TUM (7,)). Each landmark of ``ellipsoids`` wholly in front of the camera is drawn as
    its projected outline (``conic_outline``) with its closed-form box (red dashed) and
    ``labels[i]``; ``boxes`` (arrays [x1, y1, x2, y2] or ``Detection``s) in green. Image
    coordinates: origin top left, v down, pixel centres at integers.
    """
    w, h = float(camera.width), float(camera.height)
    ellipsoids = list(ellipsoids)
    if labels is not None and len(labels) != len(ellipsoids):
        raise ValueError(f"need one label per ellipsoid, got {len(labels)} for {len(ellipsoids)}")
    T_wc = _pose(T_wc)
    from matplotlib.patches import Rectangle

    fig = _figure(figsize=(w / dpi, h / dpi))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    extent = (-0.5, w - 0.5, h - 0.5, -0.5)
    img = _read_image(image)
    if img is not None:
        ax.imshow(img, extent=extent, interpolation="nearest", cmap="gray" if img.ndim == 2 else None)
    else:
        ax.set_facecolor("0.93")
    lw = max(1.0, w / 640.0 * 1.2)
    fs = max(6.0, w / 640.0 * 8.0)
    for b in boxes or []:
        box, lab = _box_of(b)
        ax.add_patch(Rectangle((box[0], box[1]), box[2] - box[0], box[3] - box[1],
                               fill=False, ec="lime", lw=lw))  # fmt: skip
        if lab:
            ax.text(box[0], box[3], f" {lab}", color="lime", fontsize=fs, va="top", clip_on=True)
    for i, e in enumerate(ellipsoids):
        landmark = Ellipsoid(*_landmark(e))
        if not bool(in_front(landmark, T_wc)):
            continue
        Cs = np.asarray(project_dual_quadric(landmark.dual_quadric(), T_wc, camera))
        try:
            c, S = conic_ellipse(Cs)
        except ValueError:
            continue
        color = _COLORS[i % len(_COLORS)]
        uv = ellipse_points(c, S, n_points)
        ax.plot(uv[:, 0], uv[:, 1], "-", color=color, lw=lw)
        r = np.sqrt(np.diag(S))
        ax.add_patch(Rectangle(tuple(c - r), 2 * r[0], 2 * r[1], fill=False, ec="red", ls="--", lw=lw))
        text = str(i) if labels is None else str(labels[i])
        ax.text(c[0] - r[0], c[1] - r[1], f"{text} ", color="red", fontsize=fs,
                ha="left", va="bottom", clip_on=True)  # fmt: skip
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_axis_off()
    return _save(fig, path, dpi)


def image_for(sequence, frame: int, detections, tolerance: float):
    """(timestamp, path) of the frame's image: the image nearest to the detections' stamp
    (else the pose's) within ``tolerance``, or None."""
    keys = np.array(sorted(sequence.images), dtype=float)
    if keys.size == 0:
        return None
    t = detections[0].timestamp if detections else float(sequence.timestamps[frame])
    k = int(np.argmin(np.abs(keys - t)))
    if abs(keys[k] - t) > tolerance:
        return None
    return float(keys[k]), sequence.images[float(keys[k])]


def write_overlays(folder, sequence, ellipsoids, poses_tum, frames=None, max_frames=None,
                   labels=None, dpi: int = 80) -> list[Path]:  # fmt: skip
    """Overlays ``folder/<timestamp>.png`` (the image's timestamp, ``repr`` of the float) for
    the frames of ``sequence`` that have detections and an image; returns the written paths.

    ``poses_tum``: the poses to project with, (N, 7) ``tx ty tz qx qy qz qw`` (or (N, 8)
    with timestamps), row = frame index, N = len(sequence). ``frames``: the frame indices
    to consider (default all); ``max_frames``: at most this many of the eligible frames,
    evenly spaced (first and last included). A frame's image is the one whose timestamp is
    nearest its detections' (within ``spdslam.io.MATCH_TOLERANCE``). Returns [] when the
    sequence has no images.
    """
    if not sequence.images:
        return []
    poses = np.asarray(poses_tum, dtype=float)
    if poses.ndim == 2 and poses.shape[1] == 8:
        poses = poses[:, 1:]
    if poses.ndim != 2 or poses.shape != (len(sequence), 7):
        raise ValueError(
            f"poses_tum must have shape ({len(sequence)}, 7) (one row per frame), got {poses.shape}"
        )
    ellipsoids = list(ellipsoids)
    by_frame: dict[int, list] = {}
    for d in sequence.detections:
        by_frame.setdefault(d.frame, []).append(d)
    candidates = range(len(sequence)) if frames is None else [int(f) for f in frames]
    jobs = []
    for f in candidates:
        if not 0 <= f < len(sequence):
            raise ValueError(f"frame {f} out of range [0, {len(sequence)})")
        dets = by_frame.get(f, [])
        if not dets:
            continue
        found = image_for(sequence, f, dets, MATCH_TOLERANCE + 1e-9)
        if found is None or not Path(found[1]).is_file():
            continue
        jobs.append((f, dets, *found))
    if max_frames is not None and len(jobs) > max_frames:
        if max_frames <= 0:
            return []
        keep = np.unique(np.round(np.linspace(0, len(jobs) - 1, int(max_frames))).astype(int))
        jobs = [jobs[k] for k in keep]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for f, dets, t, image in jobs:
        target = folder / f"{t!r}.png"
        pose = poses[f]
        out.append(plot_overlay(target, image, sequence.camera, pose, ellipsoids, dets, labels, dpi))
    return out


# --- online latency -------------------------------------------------------------------------


LATENCY_COLUMNS = ("frame", "timestamp", "seconds", "objects", "factors", "variables", "iterations", "lag")


def latency_csv(records) -> str:
    """latency.csv of an online run: a header and one row per frame (``FrameRecord``s:
    frame, timestamp (s), seconds ``add_frame`` spent on the frame, objects mapped after it,
    factors and free variables of the problem solved at it (0: none solved), LM iterations,
    and the map's lag: seconds from the frame's arrival to the end of the first optimisation
    that used it (nan: none did))."""
    lines = [",".join(LATENCY_COLUMNS)]
    for r in records:
        lines.append(f"{r.frame},{r.timestamp:.6f},{r.seconds:.6f},{r.objects},{r.factors},"
                     f"{r.variables},{r.iterations},{r.lag:.6f}")
    return "\n".join(lines) + "\n"


def plot_latency(path, records, rate: float | None = None, title: str = "", dpi: int = 110) -> Path:
    """Time per frame of an online run (log scale; frames where the problem was solved
    marked), its median and 99th percentile, the map's lag per frame (``FrameRecord.lag``,
    where known), the frame period 1/``rate`` when given, and the objects mapped (right
    axis)."""
    frame = np.array([r.frame for r in records], dtype=float)
    ms = 1e3 * np.array([r.seconds for r in records], dtype=float)
    solved = np.array([r.factors > 0 for r in records], dtype=bool)
    objects = np.array([r.objects for r in records], dtype=float)
    fig = _figure(figsize=(8.0, 4.0), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    if ms.size:
        ax.plot(frame[~solved], np.maximum(ms[~solved], 1e-3), ".", ms=2, color="tab:blue",
                label="frame (no optimisation)")
        ax.plot(frame[solved], np.maximum(ms[solved], 1e-3), ".", ms=4, color="tab:orange",
                label="frame with an optimisation")
        med, p99 = np.median(ms), np.percentile(ms, 99)
        ax.axhline(med, color="tab:green", lw=1, label=f"median {med:.3g} ms")
        ax.axhline(p99, color="tab:red", lw=1, label=f"99th percentile {p99:.3g} ms")
        lag = 1e3 * np.array([getattr(r, "lag", np.nan) for r in records], dtype=float)
        if np.isfinite(lag).any():
            ax.plot(frame, lag, lw=0.8, color="tab:purple", alpha=0.7,
                    label=f"map lag (median {np.nanmedian(lag) / 1e3:.3g} s)")
    if rate:
        ax.axhline(1e3 / rate, color="k", ls="--", lw=1, label=f"frame period at {rate:.3g} Hz")
    ax.set_yscale("log")
    ax.set_xlabel("frame")
    ax.set_ylabel("time to process, lag (ms)")
    ax.legend(loc="upper left", fontsize=7)
    ax2 = ax.twinx()
    ax2.plot(frame, objects, color="0.4", lw=1)
    ax2.set_ylabel("objects mapped", color="0.4")
    ax.set_title(title or "online mapping: time per frame")
    return _save(fig, path, dpi)
