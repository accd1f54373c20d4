"""Keyframes: the frames a run uses.

``"all"`` keeps every frame; ``"motion"`` keeps the first frame and then each frame whose
camera has moved at least ``translation`` metres or turned at least ``rotation_deg`` degrees
from the last kept one (the usual visual-SLAM keyframe rule); an integer k keeps every k-th
frame. Frames are chosen from the input trajectory alone.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["KEYFRAME_MODES", "parse_keyframes", "select_keyframes"]

KEYFRAME_MODES = ("all", "motion")
#: The "motion" rule's thresholds.
KEYFRAME_TRANSLATION = 0.05
KEYFRAME_ROTATION_DEG = 5.0


def parse_keyframes(text) -> str | int:
    """"all", "motion" or a positive integer k (every k-th frame), from a CLI string."""
    if isinstance(text, int) and not isinstance(text, bool):
        value = text
    elif str(text) in KEYFRAME_MODES:
        return str(text)
    else:
        try:
            value = int(str(text))
        except ValueError:
            value = 0
    if value < 1:
        raise ValueError(f"keyframes must be all, motion or a positive integer, got {text!r}")
    return value


def select_keyframes(poses_tum, mode="all", translation: float = KEYFRAME_TRANSLATION,
                     rotation_deg: float = KEYFRAME_ROTATION_DEG) -> np.ndarray:
    """Indices of the keyframes of a trajectory ((N, 7) rows tx ty tz qx qy qz qw)."""
    mode = parse_keyframes(mode)
    poses = np.asarray(poses_tum, float)
    n = len(poses)
    if mode == "all" or n == 0:
        return np.arange(n)
    if isinstance(mode, int):
        return np.arange(0, n, mode)
    R = Rotation.from_quat(poses[:, 3:7])
    keep, last = [0], 0
    cos_max = np.cos(np.radians(rotation_deg) / 2)
    q = R.as_quat()
    for i in range(1, n):
        moved = np.linalg.norm(poses[i, :3] - poses[last, :3]) >= translation
        turned = abs(q[i] @ q[last]) <= cos_max  # half-angle of the relative rotation
        if moved or turned:
            keep.append(i)
            last = i
    return np.asarray(keep)
