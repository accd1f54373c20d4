"""A deterministic synthetic room: many upright ellipsoid (or cuboid) objects, a closed
camera loop with odometry drift, and the boxes of the objects in every frame, optionally
truncated, missed or mixed with false boxes (``make_room_sequence``).

Conventions (as everywhere in spdslam): world +z is up and the floor is z = 0; poses are
camera-to-world ``T_wc`` (TUM ``tx ty tz qx qy qz qw``); boxes are ``[u_min, v_min, u_max,
v_max]`` in pixels; timestamps are ``k / 10`` s (10 Hz from 0.0).

Objects. Object i is an ellipsoid with one axis vertical: R = R_z(ψᵢ) (ψᵢ uniform),
radii s = s̄(label)·(1 + j·U(−1, 1)) per axis (s̄ from ``ROOM_CLASSES``, j = ``size_jitter``),
centre (x, y, s₃), so it stands on the floor. Its ground truth is the circumscribed cuboid
(centre, R, half-extents s), so a perfect estimate has IoU 1. With ``object_shape="cuboid"``
the object *is* that cuboid (the detector boxes its silhouette; the class priors say
``shape="cuboid"``) and the landmark ellipsoid (P = R diag(s²) Rᵀ, t) is the inscribed one.
Objects lie in rectangular *strips* of the square room ``[−L/2, L/2]²``, with footprint
discs of radius √(s₁² + s₂²) at least ``OBJECT_GAP`` apart (rejection sampling, largest
first), hence disjoint cuboids.

Camera. A closed counter-clockwise loop with rounded corners: along the bottom edge of a
strip, up its right end, back along its top edge, a U-turn into the next strip's bottom
aisle, ..., and back along the left wall to the start. The camera keeps ``AISLE`` metres from
every strip, ``WALL`` from the walls, and looks to the left of its motion (into the strip it
circles) with a slow pan of ±``PAN_DEG``, a downward pitch of ``PITCH_DEG`` ± ``PITCH_WOBBLE_DEG``
and a height of ``CAMERA_HEIGHT`` ± ``HEIGHT_WOBBLE`` (``look_at`` with up = +z, no roll), so
every object is seen from both sides of its strip and obliquely. With one strip (the
default room for a few objects) this is a rounded rectangle around the room looking inward;
larger rooms get more strips, so the work per frame stays bounded.

Boxes. For each frame and object, the closed-form box of the dual conic C* = M Q* Mᵀ,
M = K [R_cw | t_cw] (``geometry.project_box``); a cuboid's box is that of its 8 projected
corners t + R diag(s) σ, σ ∈ {±1}³ (``geometry.project_cuboid_box``). Both are computed in
NumPy for all kept (frame, object) pairs at once. A box is kept when the whole object is in
front (depth > ``MIN_DEPTH``: ``geometry.depth_range``, resp. every corner), its centre no deeper
than ``MAX_DEPTH`` (a detector's range; without it every object of a large room would be
seen in every frame), the camera outside it, the box inside the image with a ``MARGIN_PX``
margin and at least ``MIN_BOX_PX`` wide and high. Then N(0, ``box_noise_px``²) is added to
each coordinate and boxes no longer inside the image or no longer proper (x2 > x1, y2 > y1)
are dropped. Label = class, score 1, instance = id. Occlusion is not modelled. All (frame,
object) pairs are processed in vectorised chunks, culled first by the projected centre (or,
with truncation, by the bounding sphere against the four planes of the image edges).

Detector imperfections (all off by default). ``truncation``: the box may extend beyond the
image; it is kept when its visible part, box ∩ [0, W] × [0, H], is at least ``MIN_BOX_PX``
wide and high (no margin), and after the noise it is clipped to [0, W] × [0, H], so a
truncated box touches the image border. ``missed`` = m: round(m·n) of the n true detections,
chosen uniformly without replacement, are dropped. ``outliers`` = r: round(r·n') false
boxes are added, n' the true detections left: each has the width and height of a random
true box, its corner uniform in [0, W − w] × [0, H − h], a uniform random frame, a label
uniform over the labels present, score U(0.3, 1) and instance −1 (a known false detection,
left out by manual association). Detections stay frame-major (in a frame: true ones by
object id, then the false ones).

Drift. ``groundtruth_tum`` holds the true poses T_k; the trajectory ``poses_tum`` (the
back end's odometry/initial values) is T'₀ = T₀, T'_k = T'_{k−1} (T_{k−1}⁻¹ T_k) E_k with
E_k = (Exp(ω_k), v_k) in the frame of camera k, v_k ~ N(0, drift² I₃) metres and
ω_k ~ N(0, (drift/2)² I₃) radians per step, so it drifts like a random walk.

Randomness: independent streams spawned from ``np.random.SeedSequence(seed)`` for the objects,
their placement, the camera wobble, the drift, the box noise, the missed and the false
detections, so the same seed gives the same sequence and e.g. changing ``drift`` changes
nothing but the trajectory. ``SeedSequence.spawn(n)[:5]`` does not depend on n, so the
last two streams left the sequences of the earlier five-stream generator unchanged.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import (
    OBJECT_SHAPES,
    Camera,
    Cuboid,
    Ellipsoid,
    camera_inside,
    cuboid_depth_range,
    depth_range,
    project_box,
    project_cuboid_box,
    project_points,
)
from ..geometry.se3 import world_to_camera
from ..io import ClassPrior, Detection, GroundTruthObject, Priors, Sequence
from ._scenes import DEFAULT_CAMERA

__all__ = ["ROOM_CLASSES", "make_room_sequence"]

#: label → mean semi-axes (a, b, c) in metres, c vertical (half width, depth, height).
ROOM_CLASSES: dict[str, tuple[float, float, float]] = {
    "chair": (0.25, 0.25, 0.45),
    "table": (0.70, 0.40, 0.37),
    "cabinet": (0.45, 0.25, 0.90),
    "sofa": (0.95, 0.45, 0.42),
    "plant": (0.25, 0.25, 0.55),
    "box": (0.25, 0.20, 0.18),
    "lamp": (0.20, 0.20, 0.80),
    "bin": (0.16, 0.16, 0.25),
}

FRAME_RATE = 10.0  # Hz: timestamps k / FRAME_RATE
PRIOR_SIGMA = 0.2  # sigma of the class priors
# Layout (metres).
WALL = 0.5  # camera path to the walls
AISLE = 1.5  # camera path to the strips of objects
GAP = 1.0  # between a strip's top aisle and the next strip's bottom aisle (U-turn diameter)
CORNER = 1.0  # radius of the loop's other corners
STRIP_TARGET = 4.5  # preferred strip width
OBJECT_GAP = 0.2  # minimum free space between two objects' footprint discs
COVERAGE = 0.3  # default room: footprint discs cover this fraction of the strips
ROOM_STEP = 0.25  # default room sizes are multiples of this
# Camera motion.
CAMERA_HEIGHT, HEIGHT_WOBBLE, HEIGHT_WAVELENGTH = 1.35, 0.1, 10.0
PITCH_DEG, PITCH_WOBBLE_DEG, PITCH_WAVELENGTH = 15.0, 3.0, 7.0
PAN_DEG, PAN_WAVELENGTH = 25.0, 6.0
# Detections.
MIN_DEPTH = 0.1
MAX_DEPTH = 8.0
MARGIN_PX = 2.0
MIN_BOX_PX = 10.0

_CHUNK_PAIRS = 1 << 20  # (frame, object) pairs per vectorised chunk
_PLACE_BATCH, _PLACE_TRIES = 32, 400  # rejection sampling: candidates per batch, batches


# --- arguments ------------------------------------------------------------------------------


def _integer(name: str, value, minimum: int) -> int:
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if not ok or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _real(name: str, value, lo: float, hi: float | None = None) -> float:
    """A finite float in [lo, hi) (or ≥ lo)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    v = float(value) if ok else math.nan
    if not math.isfinite(v) or v < lo or (hi is not None and v >= hi):
        bounds = f"in [{lo:g}, {hi:g})" if hi is not None else f">= {lo:g}"
        raise ValueError(f"{name} must be a finite number {bounds}, got {value!r}")
    return v


# --- layout ---------------------------------------------------------------------------------


def _strips(L: float, min_width: float):
    """(k, width, y_bottoms) of the strips of a room of side L, or None if none fits."""
    inner = L - 2 * WALL
    length = inner - 2 * AISLE
    k = max(1, round((inner + GAP) / (STRIP_TARGET + 2 * AISLE + GAP)))
    while True:
        w = (inner - 2 * AISLE * k - GAP * (k - 1)) / k
        if w >= min_width or k == 1:
            break
        k -= 1
    if w < min_width or length < min_width:
        return None
    y0 = -L / 2 + WALL + AISLE + np.arange(k) * (w + 2 * AISLE + GAP)
    return k, w, y0


def _default_room(rho: np.ndarray) -> float:
    """Smallest multiple of ROOM_STEP whose strips hold the footprints at COVERAGE."""
    need = float(np.sum(np.pi * (rho + OBJECT_GAP / 2) ** 2)) / COVERAGE
    min_width = 2 * float(rho.max()) + OBJECT_GAP
    L = ROOM_STEP * math.ceil((2 * WALL + 2 * AISLE + min_width) / ROOM_STEP)
    while True:
        s = _strips(L, min_width)
        if s is not None and s[0] * s[1] * (L - 2 * WALL - 2 * AISLE) >= need:
            return L
        L += ROOM_STEP


def _place(rng, rho: np.ndarray, L: float, strips) -> np.ndarray:
    """Footprint centres (n, 2): uniform in the strips, discs ≥ OBJECT_GAP apart."""
    k, w, y0 = strips
    x0, x1 = -L / 2 + WALL + AISLE, L / 2 - WALL - AISLE
    xy = np.zeros((rho.size, 2))
    done_xy, done_rho = np.zeros((rho.size, 2)), np.zeros(rho.size)  # placed, in order
    for m, i in enumerate(np.argsort(-rho, kind="stable")):
        r = rho[i]
        reach2 = (r + done_rho[:m] + OBJECT_GAP) ** 2
        for _ in range(_PLACE_TRIES):
            s = rng.integers(k, size=_PLACE_BATCH)
            u = rng.uniform(size=(_PLACE_BATCH, 2))
            cand = np.stack(
                [x0 + r + u[:, 0] * (x1 - x0 - 2 * r), y0[s] + r + u[:, 1] * (w - 2 * r)], axis=1
            )
            dx = cand[:, None, 0] - done_xy[None, :m, 0]
            dy = cand[:, None, 1] - done_xy[None, :m, 1]
            ok = np.all(dx * dx + dy * dy >= reach2, axis=1)
            if ok.any():
                xy[i] = done_xy[m] = cand[np.argmax(ok)]
                done_rho[m] = r
                break
        else:
            raise ValueError(
                f"cannot place {rho.size} objects without overlap in a {L:g} m room "
                f"(object {i} did not fit); use a larger room_size or room_size=None"
            )
    return xy


# --- camera loop ----------------------------------------------------------------------------


def _loop_vertices(L: float, strips):
    """Corners (n, 2) and corner radii (n,) of the counter-clockwise camera loop."""
    k, w, y0 = strips
    x_ret, x_right = -L / 2 + WALL, L / 2 - WALL
    x_turn = x_ret + AISLE  # leftmost point of the U-turns between strips
    yb, yt = y0 - AISLE, y0 + w + AISLE
    V, r = [(x_ret, yb[0])], [CORNER]
    for j in range(k):
        V += [(x_right, yb[j]), (x_right, yt[j])]
        r += [CORNER, CORNER]
        if j < k - 1:
            V += [(x_turn, yt[j]), (x_turn, yb[j + 1])]
            r += [GAP / 2, GAP / 2]
    V.append((x_ret, yt[-1]))
    r.append(CORNER)
    return np.array(V), np.array(r)


def _sample_loop(V: np.ndarray, radii: np.ndarray, n: int):
    """Positions (n, 2), headings (n,), arc lengths (n,) and total length of n points evenly
    spaced along the closed polyline V with rounded corners, from the end of corner 0."""
    d_in = V - np.roll(V, 1, axis=0)
    d_in /= np.linalg.norm(d_in, axis=1, keepdims=True)
    d_out = np.roll(V, -1, axis=0) - V
    d_out /= np.linalg.norm(d_out, axis=1, keepdims=True)
    turn = np.sign(d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0])
    centre = V + radii[:, None] * (d_out - d_in)
    start = V + radii[:, None] * d_out  # where each arc ends and the next line starts
    theta0 = np.arctan2(-d_out[:, 1], -d_out[:, 0])
    # Pieces: line i → i+1, arc i+1, for i = 0..n−1 (arc n ≡ arc 0 closes the loop).
    nxt = np.roll(np.arange(len(V)), -1)
    line_len = np.linalg.norm((V[nxt] - radii[nxt, None] * d_in[nxt]) - start, axis=1)
    arc_len = radii[nxt] * np.abs(
        np.angle(np.exp(1j * (np.arctan2(d_out[nxt, 1], d_out[nxt, 0])
                              - np.arctan2(d_in[nxt, 1], d_in[nxt, 0]))))
    )
    lengths = np.stack([line_len, arc_len], axis=1).ravel()
    s0 = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    total = float(lengths.sum())
    s = np.arange(n) * (total / n)
    piece = np.clip(np.searchsorted(s0, s, side="right") - 1, 0, lengths.size - 1)
    idx, is_arc = piece // 2, (piece % 2) == 1
    ds = s - s0[piece]
    line_xy = start[idx] + ds[:, None] * d_out[idx]
    line_heading = np.arctan2(d_out[idx, 1], d_out[idx, 0])
    a = nxt[idx]
    th = theta0[a] + turn[a] * ds / radii[a]
    arc_xy = centre[a] + radii[a, None] * np.stack([np.cos(th), np.sin(th)], axis=1)
    arc_heading = th + turn[a] * np.pi / 2
    xy = np.where(is_arc[:, None], arc_xy, line_xy)
    heading = np.where(is_arc, arc_heading, line_heading)
    return xy, heading, s, total


def _camera_poses(rng, L: float, strips, frames: int):
    """Camera centres (F, 3) and rotations R_wc (F, 3, 3) along the loop."""
    V, radii = _loop_vertices(L, strips)
    xy, heading, s, total = _sample_loop(V, radii, frames)
    phase = rng.uniform(0.0, 2 * np.pi, size=3)

    def wave(wavelength, ph):  # periodic over the loop, so the loop closes smoothly
        cycles = max(1, round(total / wavelength))
        return np.sin(2 * np.pi * cycles * s / total + ph)

    height = CAMERA_HEIGHT + HEIGHT_WOBBLE * wave(HEIGHT_WAVELENGTH, phase[0])
    yaw = heading + np.pi / 2 + np.deg2rad(PAN_DEG) * wave(PAN_WAVELENGTH, phase[1])
    pitch = -np.deg2rad(PITCH_DEG + PITCH_WOBBLE_DEG * wave(PITCH_WAVELENGTH, phase[2]))
    # camera.look_at with up = +z: z along the view, x = z × up / ‖·‖, y = z × x.
    cp = np.cos(pitch)
    z = np.stack([cp * np.cos(yaw), cp * np.sin(yaw), np.sin(pitch)], axis=1)
    x = np.stack([np.sin(yaw), -np.cos(yaw), np.zeros_like(yaw)], axis=1)
    y = np.cross(z, x)
    R_wc = np.stack([x, y, z], axis=-1)
    centres = np.column_stack([xy, height])
    return centres, R_wc


def _tum(centres: np.ndarray, R_wc: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R_wc).as_quat()  # x y z w
    q = np.where(q[:, 3:] < 0, -q, q)
    return np.column_stack([centres, q])


# --- detections -----------------------------------------------------------------------------



def _frustum_planes(camera: Camera) -> np.ndarray:
    """Unit normals (4, 3), camera frame, of the planes through the optical centre and the
    image lines u = m, u = W − m, v = m, v = H − m (m = MIN_BOX_PX), pointing to the image:
    a point (x, y, z), z > 0, projects to u ≥ m iff f_x x + (c_x − m) z ≥ 0, and so on."""
    fx, fy, cx, cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    W, H, m = float(camera.width), float(camera.height), MIN_BOX_PX
    n = np.array([
        [fx, 0.0, cx - m], [-fx, 0.0, W - m - cx], [0.0, fy, cy - m], [0.0, -fy, H - m - cy],
    ])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _boxes(centres, R_wc, t, P, R_obj, radii, camera: Camera, shape: str, truncation: bool):
    """(frame, object, box) of every valid noise-free detection, frame-major order; boxes
    are unclipped (with ``truncation`` they may extend beyond the image)."""
    F, n_obj = centres.shape[0], t.shape[0]
    W, H = float(camera.width), float(camera.height)
    cuboid = shape == "cuboid"
    half_axes = R_obj * radii[:, None, :]  # the cuboid's half-edge vectors (columns)
    # bounding-sphere radius of each object (truncation cull)
    bound = np.linalg.norm(radii, axis=1) if cuboid else radii.max(axis=1)
    planes = _frustum_planes(camera)
    step = max(1, _CHUNK_PAIRS // n_obj)
    out_f, out_o, out_b = [], [], []
    for f0 in range(0, F, step):
        c, R = centres[f0:f0 + step], R_wc[f0:f0 + step]
        # (f, o) grid: near depth of each object, depth of its centre
        grid = (R[:, None], c[:, None])
        if cuboid:
            near = cuboid_depth_range((half_axes[None], t[None]), grid)[..., 0]
        else:
            near = depth_range(Ellipsoid(P[None], t[None]), grid)[..., 0]
        Rt = world_to_camera((R, c))  # [R_cw | t_cw]
        z = Rt[:, 2, :3] @ t.T + Rt[:, 2, 3:]
        keep = (near > MIN_DEPTH) & (z <= MAX_DEPTH)
        if truncation:
            # Cull unless the bounding sphere reaches into each of the four half-spaces
            # (a conservative test: at least MIN_BOX_PX of the outline may be visible).
            for n_c in planes:
                n_w = R @ n_c  # (f, 3): the plane normal in the world frame
                keep &= n_w @ t.T - np.sum(n_w * c, axis=1)[:, None] >= -bound
        else:
            # The centre projects inside the projected outline: cull by it first.
            uv = project_points(t, (R, c), camera)
            u, v = uv[..., 0], uv[..., 1]
            keep &= (u > MARGIN_PX) & (u < W - MARGIN_PX) & (v > MARGIN_PX) & (v < H - MARGIN_PX)
        fi, oi = np.nonzero(keep)
        if fi.size == 0:
            continue
        pose = (R[fi], c[fi])
        if cuboid:
            box = project_cuboid_box((half_axes[oi], t[oi]), pose, camera)
            local = np.einsum("nji,nj->ni", R_obj[oi], c[fi] - t[oi])  # camera in the object frame
            outside = np.any(np.abs(local) >= radii[oi], axis=1)
        else:
            landmark = Ellipsoid(P[oi], t[oi])
            box = project_box(landmark, pose, camera)
            outside = ~camera_inside(landmark, pose)
        if truncation:  # the visible part, box ∩ [0, W] × [0, H]
            ok = (
                outside
                & (np.minimum(box[:, 2], W) - np.maximum(box[:, 0], 0.0) >= MIN_BOX_PX)
                & (np.minimum(box[:, 3], H) - np.maximum(box[:, 1], 0.0) >= MIN_BOX_PX)
            )
        else:
            ok = (
                outside
                & (box[:, 0] >= MARGIN_PX)
                & (box[:, 1] >= MARGIN_PX)
                & (box[:, 2] <= W - MARGIN_PX)
                & (box[:, 3] <= H - MARGIN_PX)
                & (box[:, 2] - box[:, 0] >= MIN_BOX_PX)
                & (box[:, 3] - box[:, 1] >= MIN_BOX_PX)
            )
        out_f.append(fi[ok] + f0)
        out_o.append(oi[ok])
        out_b.append(box[ok])
    if not out_f:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4))
    return np.concatenate(out_f), np.concatenate(out_o), np.concatenate(out_b)


def _false_detections(rng, n, fi, oi, boxes, scores, frames: int, n_labels: int, W, H):
    """The detections with n false ones added, frame-major (within a frame the true ones
    first, in object order). A false box has the size (w, h) of a random true box, its corner
    uniform in [0, W − w] × [0, H − h], a uniform random frame, label index ℓ uniform
    (stored as object −1 − ℓ) and score U(0.3, 1)."""
    wh = boxes[rng.integers(fi.size, size=n)]
    wh = wh[:, 2:] - wh[:, :2]
    lo = rng.uniform(size=(n, 2)) * (np.array([W, H]) - wh)
    false_boxes = np.concatenate([lo, np.minimum(lo + wh, [W, H])], axis=1)
    false_f = rng.integers(frames, size=n)
    false_o = -1 - rng.integers(n_labels, size=n)
    false_s = rng.uniform(0.3, 1.0, size=n)
    f = np.concatenate([fi, false_f])
    order = np.argsort(f, kind="stable")
    return (
        f[order],
        np.concatenate([oi, false_o])[order],
        np.concatenate([boxes, false_boxes])[order],
        np.concatenate([scores, false_s])[order],
    )


# --- drift ----------------------------------------------------------------------------------


def _prefix_products(A: np.ndarray) -> np.ndarray:
    """[A₀, A₀A₁, A₀A₁A₂, …] of (n, 4, 4) matrices, in log₂ n batched steps."""
    P = A.copy()
    s = 1
    while s < len(P):
        P[s:] = P[:-s] @ P[s:]
        s *= 2
    return P


def _drift(rng, centres: np.ndarray, R_wc: np.ndarray, drift: float) -> np.ndarray:
    """The drifted trajectory (TUM rows) of the true poses (see the module docstring)."""
    n = centres.shape[0]
    noise = rng.standard_normal(size=(n - 1, 6))
    if drift == 0.0:
        return _tum(centres, R_wc)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R_wc, centres, 1.0
    Rp = np.swapaxes(R_wc[:-1], 1, 2)
    U = np.zeros((n - 1, 4, 4))
    U[:, :3, :3] = Rp @ R_wc[1:]
    U[:, :3, 3] = np.einsum("nij,nj->ni", Rp, centres[1:] - centres[:-1])
    U[:, 3, 3] = 1.0
    E = np.zeros((n - 1, 4, 4))
    E[:, :3, :3] = Rotation.from_rotvec((drift / 2) * noise[:, 3:]).as_matrix()
    E[:, :3, 3] = drift * noise[:, :3]
    E[:, 3, 3] = 1.0
    T_odo = _prefix_products(np.concatenate([T[:1], U @ E]))
    return _tum(T_odo[:, :3, 3], T_odo[:, :3, :3])


def drifted_sequence(seq: Sequence, sigma_t: float, sigma_r: float, seed: int = 0) -> Sequence:
    """``seq`` (a recording, e.g. with motion-capture poses) made a drifting odometry: each
    relative motion Tᵢ₋₁⁻¹Tᵢ composed with Exp(ε), ε = (v, ω) ~ N(0, diag(σ_t² I₃, σ_r² I₃))
    (m, rad per frame step; for each step three draws of ω, then three of v, from
    ``numpy.random.default_rng(seed)``), chained from the first pose; its priors say
    ``trajectory_absolute_sigma: [.inf, .inf]`` (no bound on each pose). The ground truth
    and everything else are unchanged."""
    import dataclasses

    sigma_t = _real("sigma_t", sigma_t, 0.0)
    sigma_r = _real("sigma_r", sigma_r, 0.0)
    rows = np.asarray(seq.poses_tum, dtype=float)
    n = len(rows)
    priors = (seq.priors or Priors()).replace(trajectory_absolute_sigma=[np.inf, np.inf])
    if n < 2:
        return dataclasses.replace(seq, priors=priors)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = Rotation.from_quat(rows[:, 3:7]).as_matrix()
    T[:, :3, 3], T[:, 3, 3] = rows[:, :3], 1.0
    noise = np.random.default_rng(seed).standard_normal(size=(n - 1, 6))
    E = np.zeros((n - 1, 4, 4))
    E[:, :3, :3] = Rotation.from_rotvec(sigma_r * noise[:, :3]).as_matrix()
    E[:, :3, 3], E[:, 3, 3] = sigma_t * noise[:, 3:], 1.0
    U = np.linalg.inv(T[:-1]) @ T[1:]
    chained = _prefix_products(np.concatenate([T[:1], U @ E]))
    return dataclasses.replace(seq, poses_tum=_tum(chained[:, :3, 3], chained[:, :3, :3]), priors=priors)


# --- the sequence ---------------------------------------------------------------------------


def make_room_sequence(
    seed: int = 0,
    frames: int = 120,
    objects: int = 8,
    *,
    box_noise_px: float = 2.0,
    drift: float = 0.005,
    room_size: float | None = None,
    camera: Camera | None = None,
    size_jitter: float = 0.1,
    name: str = "demo_room",
    truncation: bool = False,
    outliers: float = 0.0,
    missed: float = 0.0,
    object_shape: str = "ellipsoid",
) -> Sequence:
    """A synthetic room sequence (see the module docstring for the model).

    ``seed`` (int ≥ 0) fixes everything; ``frames`` ≥ 3 poses 0.1 s apart along one closed
    loop; ``objects`` ≥ 1 upright ellipsoids, labels spread evenly over ``ROOM_CLASSES`` in
    random order; ``box_noise_px`` the σ of the box noise (pixels per coordinate); ``drift``
    the odometry noise per step (σ = drift metres, drift/2 radians); ``room_size`` the side
    of the square room in metres (None: the smallest multiple of 0.25 m whose strips the
    objects' footprints cover at 30 %; too small a room raises ``ValueError``); ``camera``
    the intrinsics (default ``simulation.DEFAULT_CAMERA``, 640×480, f = 500 px);
    ``size_jitter`` ∈ [0, 1) the relative spread of the radii about the class means.

    Detector imperfections (all off by default, when the sequence for a seed is unchanged):
    ``truncation`` keeps objects partly outside the image, their boxes clipped to the image;
    ``outliers`` ∈ [0, 1) adds round(outliers · n) false boxes (instance −1), n the number of
    true detections; ``missed`` ∈ [0, 1) drops that fraction of the true detections;
    ``object_shape`` ``"ellipsoid"`` or ``"cuboid"`` (objects are boxes, boxed by their 8
    projected corners).

    Returns a ``Sequence`` with the drifted trajectory, the detections (frame-major), ``objects_gt``
    (the cuboids: circumscribing the ellipsoids, or the cuboid objects themselves),
    ``groundtruth_tum`` (the true poses) and ``priors`` (the floor z = 0, up = +z, a
    ``ClassPrior(class mean, 0.2, object_shape)`` per label present).
    """
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    frames = _integer("frames", frames, 3)
    objects = _integer("objects", objects, 1)
    box_noise_px = _real("box_noise_px", box_noise_px, 0.0)
    drift = _real("drift", drift, 0.0)
    size_jitter = _real("size_jitter", size_jitter, 0.0, 1.0)
    if room_size is not None:
        room_size = _real("room_size", room_size, 0.0)
        if room_size <= 0:
            raise ValueError(f"room_size must be positive, got {room_size!r}")
    if camera is None:
        camera = DEFAULT_CAMERA
    if not isinstance(camera, Camera) or not all(
        isinstance(getattr(camera, k), numbers.Real)
        for k in ("fx", "fy", "cx", "cy", "width", "height")
    ):
        raise ValueError(f"camera must be a Camera with scalar intrinsics, got {camera!r}")
    if not isinstance(name, str) or not name or any(ch.isspace() for ch in name):
        raise ValueError(f"name must be a non-empty string without whitespace, got {name!r}")
    if not isinstance(truncation, (bool, np.bool_)):
        raise ValueError(f"truncation must be True or False, got {truncation!r}")
    truncation = bool(truncation)
    outliers = _real("outliers", outliers, 0.0, 1.0)
    missed = _real("missed", missed, 0.0, 1.0)
    if object_shape not in OBJECT_SHAPES:
        raise ValueError(
            f"object_shape must be one of {', '.join(OBJECT_SHAPES)}, got {object_shape!r}"
        )

    # SeedSequence.spawn(n)[:5] does not depend on n: the first five streams are those of
    # the generator before the detector imperfections existed.
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(7)]
    rng_obj, rng_place, rng_cam, rng_drift, rng_box, rng_missed, rng_false = streams

    # Objects: labels, radii, yaw.
    names = list(ROOM_CLASSES)
    label_idx = rng_obj.permutation(np.arange(objects) % len(names))
    mean = np.array([ROOM_CLASSES[n] for n in names])[label_idx]
    radii = mean * (1.0 + size_jitter * rng_obj.uniform(-1.0, 1.0, size=(objects, 3)))
    yaw = rng_obj.uniform(0.0, 2 * np.pi, size=objects)
    rho = np.hypot(radii[:, 0], radii[:, 1])  # footprint radius of the cuboid

    # Room and placement.
    min_width = 2 * float(rho.max()) + OBJECT_GAP
    L = _default_room(rho) if room_size is None else room_size
    strips = _strips(L, min_width)
    if strips is None:
        need = 2 * WALL + 2 * AISLE + min_width
        raise ValueError(
            f"room_size {L:g} m is too small for the camera aisles and the largest object "
            f"(needs at least {need:.2f} m)"
        )
    xy = _place(rng_place, rho, L, strips)
    cy_, sy_ = np.cos(yaw), np.sin(yaw)
    zeros, ones = np.zeros(objects), np.ones(objects)
    R_obj = np.stack(
        [np.stack([cy_, sy_, zeros], 1), np.stack([-sy_, cy_, zeros], 1), np.stack([zeros, zeros, ones], 1)],
        axis=-1,
    )  # columns = axes
    t_obj = np.column_stack([xy, radii[:, 2]])
    P_obj = np.einsum("nij,nj,nkj->nik", R_obj, radii**2, R_obj)

    # Camera loop, true poses and the drifted trajectory.
    centres, R_wc = _camera_poses(rng_cam, L, strips, frames)
    timestamps = np.arange(frames) / FRAME_RATE
    gt = _tum(centres, R_wc)
    poses = _drift(rng_drift, centres, R_wc, drift)

    # Detections.
    fi, oi, boxes = _boxes(
        centres, R_wc, t_obj, P_obj, R_obj, radii, camera, object_shape, truncation
    )
    boxes = boxes + box_noise_px * rng_box.standard_normal(size=boxes.shape)
    W, H = float(camera.width), float(camera.height)
    if truncation:
        boxes = np.clip(boxes, 0.0, [W, H, W, H])
    ok = (
        (boxes[:, 2] > boxes[:, 0])
        & (boxes[:, 3] > boxes[:, 1])
        & (boxes[:, 0] >= 0)
        & (boxes[:, 1] >= 0)
        & (boxes[:, 2] <= W)
        & (boxes[:, 3] <= H)
    )
    fi, oi, boxes = fi[ok], oi[ok], boxes[ok]
    if missed > 0.0:
        drop = rng_missed.choice(fi.size, size=round(missed * fi.size), replace=False)
        kept = np.ones(fi.size, bool)
        kept[drop] = False
        fi, oi, boxes = fi[kept], oi[kept], boxes[kept]
    labels = [names[i] for i in label_idx]
    present = sorted(set(labels), key=names.index)
    scores = np.ones(fi.size)
    n_false = round(outliers * fi.size)
    if n_false:
        fi, oi, boxes, scores = _false_detections(
            rng_false, n_false, fi, oi, boxes, scores, frames, len(present), W, H
        )
    boxes.setflags(write=False)
    ts = timestamps.tolist()
    # oi ≥ 0: object oi; oi < 0: a false detection of label present[−oi − 1]
    detections = [
        Detection(f, ts[f], b, labels[o] if o >= 0 else present[-o - 1], s, max(o, -1))
        for f, o, b, s in zip(fi.tolist(), oi.tolist(), boxes, scores.tolist())
    ]

    objects_gt = [
        GroundTruthObject(i, labels[i], Cuboid(t_obj[i], R_obj[i], radii[i])) for i in range(objects)
    ]
    priors = Priors(
        support_planes=[[0.0, 0.0, 1.0, 0.0]],
        up=[0.0, 0.0, 1.0],
        classes={n: ClassPrior(ROOM_CLASSES[n], PRIOR_SIGMA, object_shape) for n in present},
        # the generator knows how accurate its odometry is (a floor keeps σ > 0 at drift 0):
        # a random walk with no loop closure, so no bound on each pose
        trajectory_sigma=[max(drift, 1e-4), max(drift / 2, 1e-4)],
        trajectory_absolute_sigma=[np.inf, np.inf],
    )
    return Sequence(
        name=name,
        camera=camera,
        timestamps=timestamps,
        poses_tum=poses,
        detections=detections,
        objects_gt=objects_gt,
        groundtruth_tum=np.column_stack([timestamps, gt]),
        priors=priors,
    )
