"""The TUM fr3_cabinet layout (EllipsoidSLAM's reference sequence) read into the sequence model."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..geometry import Cuboid
from ._formats import SequenceFormat
from ._oaslam import read_opencv_camera
from ._parse import (
    SequenceFormatError,
    check_columns,
    match_stamp,
    optional,
    parse_box,
    parse_integer,
    parse_number,
    read_images,
    read_tum,
    required,
    token_rows,
)
from ._sequence import Detection, GroundTruthObject, Priors, Sequence

__all__ = ["Fr3CabinetFolder", "import_fr3_cabinet", "is_fr3_cabinet", "COCO_LABELS",
           "FR3_TRAJECTORY_SIGMA"]

#: Per-step accuracy (m, rad) given to the fr3_cabinet trajectory: motion capture.
FR3_TRAJECTORY_SIGMA = (1e-4, 1e-4)

#: COCO class indices (YOLO numbering) with a name in the importer; others become "class<k>".
COCO_LABELS = {28: "suitcase"}


def is_fr3_cabinet(folder) -> bool:
    """True for the TUM fr3_cabinet layout (a ``bbox/`` folder and ``truth_objects.txt``)."""
    return Fr3CabinetFolder.claims(Path(folder))


def _coco_label(k: int) -> str:
    return COCO_LABELS.get(k, f"class{k}")


def import_fr3_cabinet(folder) -> Sequence:
    """The TUM fr3_cabinet layout as a :class:`Sequence`.

    - ``groundtruth.txt`` gives the poses: the trajectory (and ``groundtruth_tum``);
    - ``bbox/<timestamp>.txt`` rows ``id x1 y1 x2 y2 label score instance`` (label a COCO
      class index: 28 → "suitcase", others "class<k>"); empty files are frames without
      detections;
    - ``TUM3.yaml`` intrinsics (``Camera.fx: …`` lines; 640×480 unless given);
    - ``truth_objects.txt`` rows ``x y z yaw hx hy hz`` → ``Cuboid.from_yaw``; the object's id
      is its row index and its label that of the detections with that instance;
    - priors: the floor z = 0 ([0, 0, 1, 0]), up = +z, and ``trajectory_sigma`` =
      (1e-4 m, 1e-4 rad) per step: the trajectory is the motion-capture ground truth;
    - ``rgb.txt`` images when present.
    """
    folder = Path(folder)
    for req in ("groundtruth.txt", "TUM3.yaml", "truth_objects.txt"):
        required(folder, req)
    if not (folder / "bbox").is_dir():
        raise SequenceFormatError(folder / "bbox", None, "a required folder bbox/", "no such folder")
    camera, _ = read_opencv_camera(folder / "TUM3.yaml")  # its distortion is 0
    traj = read_tum(folder / "groundtruth.txt", str(folder / "groundtruth.txt"))
    timestamps = traj[:, 0]

    files = []
    for f in (folder / "bbox").iterdir():
        if f.suffix != ".txt":
            continue
        required(f.parent, f.name)  # a regular file (not a directory named 1.0.txt)
        try:
            t = float(f.stem)
        except ValueError:
            raise SequenceFormatError(f, None, "a file named <timestamp>.txt", repr(f.name)) from None
        if not math.isfinite(t):
            raise SequenceFormatError(f, None, "a file named <timestamp>.txt", repr(f.name))
        files.append((t, f))
    files.sort()
    layout = "id x1 y1 x2 y2 label score instance"
    detections = []
    for t, f in files:
        name = str(f)
        frame = None
        for line, tok in token_rows(f, name):
            check_columns(name, line, tok, (8,), layout)
            parse_integer(name, line, tok[0], "id")
            box = parse_box(name, line, tok[1:5], camera=camera)
            cls = parse_integer(name, line, tok[5], "label (a COCO class index)")
            score = parse_number(name, line, tok[6], "score")
            inst = parse_integer(name, line, tok[7], "instance")
            if frame is None:
                frame = match_stamp(name, line, t, timestamps)
            detections.append(Detection(frame, t, box, _coco_label(cls), score, inst))

    labels: dict[int | None, set[str]] = {}
    for d in detections:
        labels.setdefault(d.instance, set()).add(d.label)
    objects = []
    name = str(folder / "truth_objects.txt")
    for i, (line, tok) in enumerate(token_rows(folder / "truth_objects.txt", name)):
        check_columns(name, line, tok, (7,), "x y z yaw hx hy hz")
        v = [parse_number(name, line, t, f) for t, f in zip(tok, "x y z yaw hx hy hz".split())]
        if not all(h > 0 for h in v[4:]):
            raise SequenceFormatError(name, line, "positive half-extents hx hy hz", " ".join(tok[4:]))
        lab = labels.get(i, set())
        label = next(iter(lab)) if len(lab) == 1 else "object"
        objects.append(GroundTruthObject(i, label, Cuboid.from_yaw(v[:3], v[3], v[4:])))

    images = None
    if optional(folder, "rgb.txt"):
        images = read_images(folder / "rgb.txt", folder)
    priors = Priors(
        [np.array([0.0, 0.0, 1.0, 0.0])], np.array([0.0, 0.0, 1.0]), {}, np.array(FR3_TRAJECTORY_SIGMA)
    )
    return Sequence(
        folder.name, camera, timestamps, traj[:, 1:], detections, objects, traj.copy(), priors, images
    )


class Fr3CabinetFolder(SequenceFormat):
    """The TUM fr3_cabinet layout (``import_fr3_cabinet``)."""

    name = "fr3_cabinet"
    title = "a TUM fr3_cabinet-style folder"
    layout = "bbox/ and truth_objects.txt"
    docs = "The TUM fr3_cabinet importer"

    @classmethod
    def claims(cls, path: Path) -> bool:
        return (path / "bbox").is_dir() and (path / "truth_objects.txt").is_file()

    @classmethod
    def read(cls, path: Path, **options) -> Sequence:
        return import_fr3_cabinet(path)
