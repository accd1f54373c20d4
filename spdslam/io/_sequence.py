"""The sequence model: camera, trajectory, detections, measured ellipsoids, priors and the
optional ground truth, as frozen, validated NumPy data (files: ``_readers``, ``_writers``;
format: docs/formats.md). Nothing here runs JAX code.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from dataclasses import replace as _dataclass_replace
from pathlib import Path

import numpy as np

from ..geometry import Camera, Cuboid
from ._classes import builtin_class_prior
from ._frozen import arrays_close, frozen_array

__all__ = [
    "Detection",
    "EllipsoidDetection",
    "GroundTruthObject",
    "Priors",
    "Sequence",
    "without_class_table",
]

# --- data classes ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Detection:
    """A 2D box ``[x1, y1, x2, y2]`` (pixels) seen at trajectory index ``frame``."""

    frame: int
    timestamp: float
    box: np.ndarray
    label: str
    score: float
    instance: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "timestamp", float(self.timestamp))
        object.__setattr__(self, "box", frozen_array(self.box, (4,)))
        object.__setattr__(self, "label", str(self.label))
        object.__setattr__(self, "score", float(self.score))
        if self.instance is not None:
            object.__setattr__(self, "instance", int(self.instance))

    def __eq__(self, other):
        if not isinstance(other, Detection):
            return NotImplemented
        return (
            self.frame == other.frame
            and self.label == other.label
            and self.instance == other.instance
            and arrays_close(self.timestamp, other.timestamp)
            and arrays_close(self.score, other.score)
            and arrays_close(self.box, other.box)
        )


@dataclass(frozen=True, eq=False)
class EllipsoidDetection:
    """A whole ellipsoid measured at trajectory index ``frame`` (an RGB-D or LiDAR front
    end), in that frame's CAMERA coordinates: ``center`` (3,), ``rotation`` (3×3, columns =
    the axes, det +1) and ``radii`` (3,) the semi-axes along them, so that
    P = R diag(radii²) Rᵀ. A reflection (det −1) describes the same ellipsoid: its third
    axis is negated."""

    frame: int
    timestamp: float
    label: str
    rotation: np.ndarray
    center: np.ndarray
    radii: np.ndarray
    instance: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "frame", int(self.frame))
        object.__setattr__(self, "timestamp", float(self.timestamp))
        object.__setattr__(self, "label", str(self.label))
        R = np.array(self.rotation, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6):
            raise ValueError(f"rotation must be an orthonormal 3x3 matrix, got {R.tolist()}")
        if np.linalg.det(R) < 0:
            R[:, 2] = -R[:, 2]
        object.__setattr__(self, "rotation", frozen_array(R, (3, 3)))
        c = frozen_array(self.center, (3,))
        r = frozen_array(self.radii, (3,))
        if not np.all(np.isfinite(c)):
            raise ValueError(f"center must be finite, got {c.tolist()}")
        if not (np.all(np.isfinite(r)) and np.all(r > 0)):
            raise ValueError(f"radii must be positive, got {r.tolist()}")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "radii", r)
        if self.instance is not None:
            object.__setattr__(self, "instance", int(self.instance))

    @property
    def P(self) -> np.ndarray:
        """The shape matrix R diag(radii²) Rᵀ (camera frame)."""
        return (self.rotation * self.radii**2) @ self.rotation.T

    def __eq__(self, other):
        if not isinstance(other, EllipsoidDetection):
            return NotImplemented
        return (
            self.frame == other.frame
            and self.label == other.label
            and self.instance == other.instance
            and arrays_close(self.timestamp, other.timestamp)
            and arrays_close(self.rotation, other.rotation)
            and arrays_close(self.center, other.center)
            and arrays_close(self.radii, other.radii)
        )


@dataclass(frozen=True, eq=False)
class GroundTruthObject:
    """A ground-truth object: its id, class label and oriented cuboid (world frame)."""

    id: int
    label: str
    cuboid: Cuboid

    def __eq__(self, other):
        if not isinstance(other, GroundTruthObject):
            return NotImplemented
        a, b = self.cuboid, other.cuboid
        return (
            int(self.id) == int(other.id)
            and self.label == other.label
            and arrays_close(a.center, b.center)
            and arrays_close(a.rotation, b.rotation)
            and arrays_close(a.half_extents, b.half_extents)
        )


@dataclass(frozen=True, eq=False)
class Priors:
    """Scene priors: support planes ``[a, b, c, d]`` (ax + by + cz + d = 0), the up
    direction, per-class size priors, and the trajectory's accuracy: of its relative motion
    per frame step, ``trajectory_sigma = (σ_t m, σ_r rad)`` (None: estimated from the
    trajectory itself), and of each pose, ``trajectory_absolute_sigma`` (a globally
    consistent trajectory, e.g. a SLAM's with loop closures; None: the back end's default;
    infinite: a free random walk, e.g. odometry that drifts).

    ``builtin_classes``: classes without an entry in ``classes`` take the built-in table's
    (``spdslam.io.BUILTIN_CLASSES``, typical sizes of the indoor COCO-80 classes); see
    :meth:`class_prior`."""

    support_planes: list = field(default_factory=list)
    up: np.ndarray | None = None
    classes: dict = field(default_factory=dict)
    trajectory_sigma: np.ndarray | None = None
    builtin_classes: bool = True
    trajectory_absolute_sigma: np.ndarray | None = None

    def __post_init__(self):
        if self.trajectory_sigma is not None:
            ts = frozen_array(self.trajectory_sigma, (2,))
            if not (np.all(np.isfinite(ts)) and np.all(ts > 0)):
                raise ValueError(f"trajectory_sigma must be 2 positive numbers, got {ts.tolist()}")
            object.__setattr__(self, "trajectory_sigma", ts)
        if self.trajectory_absolute_sigma is not None:
            ta = frozen_array(self.trajectory_absolute_sigma, (2,))
            if not (np.all(~np.isnan(ta)) and np.all(ta > 0)):
                raise ValueError("trajectory_absolute_sigma must be 2 positive numbers (inf allowed), "
                                 f"got {ta.tolist()}")
            object.__setattr__(self, "trajectory_absolute_sigma", ta)
        object.__setattr__(
            self, "support_planes", [frozen_array(p, (4,)) for p in self.support_planes]
        )
        if self.up is not None:
            object.__setattr__(self, "up", frozen_array(self.up, (3,)))
        object.__setattr__(self, "classes", dict(self.classes))
        object.__setattr__(self, "builtin_classes", bool(self.builtin_classes))

    def class_prior(self, label):
        """The ``ClassPrior`` of ``label``: its entry in ``classes``, else the built-in
        table's when ``builtin_classes``, else None."""
        cp = self.classes.get(label)
        if cp is None and self.builtin_classes:
            cp = builtin_class_prior(label)
        return cp

    def replace(self, **changes) -> "Priors":
        """A copy with the given fields replaced."""
        import dataclasses

        return dataclasses.replace(self, **changes)

    def up_and_planes(self):
        """(unit up or None, support planes (k, 4) with unit normals facing up, or None).

        Up is ``up``, else the first support plane's normal: the one rule every stage uses.
        """
        planes = None
        if self.support_planes:
            planes = np.array([np.asarray(p, dtype=float) for p in self.support_planes])
            planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        up = self.up if self.up is not None else (None if planes is None else planes[0, :3])
        if up is None:
            return None, planes
        up = np.asarray(up, dtype=float) / np.linalg.norm(up)
        if planes is not None:
            planes = np.where((planes[:, :3] @ up < 0)[:, None], -planes, planes)
        return up, planes

    def __eq__(self, other):
        if not isinstance(other, Priors):
            return NotImplemented
        if len(self.support_planes) != len(other.support_planes):
            return False
        if not all(arrays_close(a, b) for a, b in zip(self.support_planes, other.support_planes)):
            return False
        if (self.up is None) != (other.up is None):
            return False
        if self.up is not None and not arrays_close(self.up, other.up):
            return False
        if (self.trajectory_sigma is None) != (other.trajectory_sigma is None):
            return False
        if self.trajectory_sigma is not None and not arrays_close(self.trajectory_sigma, other.trajectory_sigma):
            return False
        a, b = self.trajectory_absolute_sigma, other.trajectory_absolute_sigma
        if (a is None) != (b is None) or (a is not None and not (
                np.array_equal(np.isinf(a), np.isinf(b))
                and arrays_close(np.where(np.isinf(a), 0, a), np.where(np.isinf(b), 0, b)))):
            return False
        return self.classes == other.classes and self.builtin_classes == other.builtin_classes


@dataclass(frozen=True, eq=False)
class Sequence:
    """A sequence: camera, trajectory (TUM rows, camera-to-world), detections and the
    optional ground truth, priors, images and measured ellipsoids
    (:class:`EllipsoidDetection`, ``ellipsoids.txt``).

    ``segments``: the first frame of each recording after the first, in a sequence joined
    from several (``mapping.joined_sequence``): their trajectories are not linked by odometry,
    and a later recording's poses move together, placed by the objects it shares with the
    first. Not written to a sequence folder."""

    name: str
    camera: Camera
    timestamps: np.ndarray
    poses_tum: np.ndarray
    detections: list
    objects_gt: list | None = None
    groundtruth_tum: np.ndarray | None = None
    priors: Priors | None = None
    images: dict | None = None
    ellipsoids: list | None = None
    segments: tuple = ()

    def __post_init__(self):
        t = frozen_array(self.timestamps)
        if t.ndim != 1:
            raise ValueError(f"timestamps must have shape (N,), got {t.shape}")
        object.__setattr__(self, "timestamps", t)
        seg = tuple(int(k) for k in self.segments)
        if any(not 0 < k < t.size for k in seg) or any(b <= a for a, b in zip(seg, seg[1:])):
            raise ValueError(f"segments must be increasing frame indices in 1…{t.size - 1}, got {list(seg)}")
        object.__setattr__(self, "segments", seg)
        object.__setattr__(self, "poses_tum", frozen_array(self.poses_tum, (t.size, 7)))
        object.__setattr__(self, "detections", list(self.detections))
        if self.objects_gt is not None:
            object.__setattr__(self, "objects_gt", list(self.objects_gt))
        if self.ellipsoids is not None:
            object.__setattr__(self, "ellipsoids", list(self.ellipsoids))
        if self.groundtruth_tum is not None:
            g = frozen_array(self.groundtruth_tum)
            if g.ndim != 2 or g.shape[1] != 8:
                raise ValueError(f"groundtruth_tum must have shape (M, 8), got {g.shape}")
            object.__setattr__(self, "groundtruth_tum", g)
        if self.images is not None:
            object.__setattr__(
                self, "images", {float(k): Path(v) for k, v in self.images.items()}
            )

    def __len__(self) -> int:
        return int(self.timestamps.size)

    def subset(self, frames) -> "Sequence":
        """The sequence restricted to the trajectory indices ``frames`` (increasing): their
        poses, detections and measured ellipsoids, renumbered; ground truth, priors and
        images unchanged."""
        import dataclasses

        frames = np.asarray(frames, dtype=int)
        if frames.ndim != 1 or np.any(np.diff(frames) <= 0) or (
                frames.size and (frames[0] < 0 or frames[-1] >= len(self))):
            raise ValueError(f"frames must be increasing indices in 0…{len(self) - 1}")
        new = np.full(len(self), -1)
        new[frames] = np.arange(frames.size)
        dets = [dataclasses.replace(d, frame=int(new[d.frame])) for d in self.detections
                if new[d.frame] >= 0]
        ells = None if self.ellipsoids is None else [
            dataclasses.replace(e, frame=int(new[e.frame])) for e in self.ellipsoids
            if new[e.frame] >= 0]
        # a segment starts at the first kept frame at or after its start
        starts = sorted({int(k) for k in np.searchsorted(frames, self.segments)} - {0, frames.size})
        return dataclasses.replace(self, timestamps=self.timestamps[frames],
                                   poses_tum=self.poses_tum[frames], detections=dets,
                                   ellipsoids=ells, segments=tuple(starts))

    def detection_indices(self, tracks) -> list:
        """For each track (``id``, ``frames`` (k,), ``boxes`` (k, 4)), the indices in
        ``detections`` of its (frame, box) pairs; raises ``ValueError`` for a pair that is no
        detection or a detection used twice."""
        lookup: dict = {}
        for i, d in enumerate(self.detections):
            lookup.setdefault((d.frame, np.asarray(d.box, dtype=float).tobytes()), []).append(i)
        used = np.zeros(len(self.detections), bool)
        out = []
        for tr in tracks:
            frames = np.asarray(tr.frames, dtype=int).reshape(-1)
            boxes = np.asarray(tr.boxes, dtype=float).reshape(-1, 4)
            if frames.size != boxes.shape[0]:
                raise ValueError(f"track {tr.id}: {frames.size} frames but {boxes.shape[0]} boxes")
            idx = []
            for f, b in zip(frames.tolist(), boxes):
                free = [i for i in lookup.get((f, b.tobytes()), []) if not used[i]]
                if not free:
                    raise ValueError(
                        f"track {tr.id}: frame {f} box {b.tolist()} is not a detection of the "
                        "sequence (or is already in another track)"
                    )
                used[free[0]] = True
                idx.append(free[0])
            out.append(np.array(idx, dtype=int))
        return out

    def detections_at(self, frame: int) -> list:
        """The detections of trajectory index ``frame``."""
        return [d for d in self.detections if d.frame == frame]

    def ellipsoids_at(self, frame: int) -> list:
        """The measured ellipsoids of trajectory index ``frame`` (none without the file)."""
        return [e for e in self.ellipsoids or () if e.frame == frame]

    def __eq__(self, other):
        if not isinstance(other, Sequence):
            return NotImplemented

        def opt(a, b, eq):
            if (a is None) != (b is None):
                return False
            return a is None or eq(a, b)

        return (
            self.name == other.name
            and self.segments == other.segments
            and self.camera == other.camera
            and arrays_close(self.timestamps, other.timestamps)
            and arrays_close(self.poses_tum, other.poses_tum)
            and self.detections == other.detections
            and opt(self.objects_gt, other.objects_gt, lambda a, b: a == b)
            and opt(self.groundtruth_tum, other.groundtruth_tum, arrays_close)
            and opt(self.priors, other.priors, lambda a, b: a == b)
            and opt(self.ellipsoids, other.ellipsoids, lambda a, b: a == b)
            and opt(
                self.images,
                other.images,
                lambda a, b: len(a) == len(b)
                and all(
                    arrays_close(ka, kb) and Path(va) == Path(vb)
                    for (ka, va), (kb, vb) in zip(sorted(a.items()), sorted(b.items()))
                ),
            )
        )


def without_class_table(seq: Sequence) -> Sequence:
    """``seq`` with the built-in table turned off (``Priors.builtin_classes = False``)."""
    priors = Priors(builtin_classes=False) if seq.priors is None else \
        seq.priors.replace(builtin_classes=False)
    return _dataclass_replace(seq, priors=priors)
