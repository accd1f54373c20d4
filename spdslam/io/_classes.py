"""Built-in class knowledge: typical sizes of the common indoor COCO-80 classes.

Each entry is a :class:`ClassPrior`: semi-axes = half the width, depth and height of a
common product of the class (``CLASS_SOURCES`` says which, with the standard or size class
it follows; the shape and size factors are blind to the axes' order), and a spread
``sigma``, the relative standard deviation of a dimension across instances of the class
(used by the initialisation; the factors' own sigmas are the run's ``shape`` and ``size``).
The numbers are written down once from those sources, never fitted to a sequence.

Every built-in class has the ellipsoid silhouette, as in the paper (and as the ground truth
of its real sequences): the ellipsoid with the product's half-dimensions as semi-axes is
inscribed in its bounding box. The cuboid silhouette is for priors a user states
(``priors.yaml``: ``shape: cuboid``); docs/sequences.md measures both silhouettes on
fr2_desk.
``priors.yaml`` overrides any entry (``classes: {label: …}``), ``builtin_classes: false``
turns the table off.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import OBJECT_SHAPES
from ._frozen import arrays_close, frozen_array

__all__ = ["ClassPrior", "BUILTIN_CLASSES", "CLASS_SOURCES", "builtin_class_prior", "class_prior"]

@dataclass(frozen=True, eq=False)
class ClassPrior:
    """Prior of a class: radii (3,), their standard deviation ``sigma``, and the ``shape``
    whose silhouette the detector boxes (``"ellipsoid"`` or ``"cuboid"``: box-like objects
    such as cabinets, monitors or tables; the radii are then the cuboid's half-extents)."""

    radii: np.ndarray
    sigma: float
    shape: str = "ellipsoid"

    def __post_init__(self):
        object.__setattr__(self, "radii", frozen_array(self.radii, (3,)))
        object.__setattr__(self, "sigma", float(self.sigma))
        if self.shape not in OBJECT_SHAPES:
            raise ValueError(f"shape must be one of {', '.join(OBJECT_SHAPES)}, got {self.shape!r}")

    def __eq__(self, other):
        if not isinstance(other, ClassPrior):
            return NotImplemented
        return (
            arrays_close(self.radii, other.radii)
            and arrays_close(self.sigma, other.sigma)
            and self.shape == other.shape
        )



#: label → (full width, depth, height in metres, relative spread, source).
_TABLE = {
    "person": (0.45, 0.28, 1.70, 0.15,
               "adult standing: stature ≈ 1.70 m, shoulder breadth ≈ 0.45 m (ANSUR II means)"),
    "bench": (1.50, 0.40, 0.45, 0.3, "park/hall bench: 1.5 m long, seat height 0.45 m"),
    "cat": (0.45, 0.20, 0.25, 0.3, "domestic cat, body length ≈ 0.46 m"),
    "dog": (0.80, 0.25, 0.60, 0.4, "medium dog, shoulder height ≈ 0.55 m"),
    "backpack": (0.30, 0.20, 0.45, 0.25, "daypack, 20–25 l (≈ 30 × 20 × 45 cm)"),
    "handbag": (0.30, 0.14, 0.24, 0.3, "medium handbag"),
    "suitcase": (0.40, 0.20, 0.55, 0.25, "cabin suitcase, IATA size limit 55 × 40 × 20 cm"),
    "sports_ball": (0.22, 0.22, 0.22, 0.2, "football size 5: circumference 68–70 cm"),
    "bottle": (0.065, 0.065, 0.21, 0.3, "0.5 l PET bottle: Ø 65 mm, 205–215 mm tall"),
    "wine_glass": (0.08, 0.08, 0.20, 0.2, "standard wine glass: bowl Ø 80 mm, 200 mm tall"),
    "cup": (0.085, 0.085, 0.095, 0.2, "11 oz mug: Ø 82 mm, 95 mm tall"),
    "fork": (0.19, 0.025, 0.015, 0.2, "table fork: 190 mm long"),
    "knife": (0.23, 0.02, 0.01, 0.2, "table knife: 230 mm long"),
    "spoon": (0.18, 0.04, 0.02, 0.2, "table spoon: 180 mm long, bowl 40 mm wide"),
    "bowl": (0.15, 0.15, 0.07, 0.3, "cereal bowl: Ø 150 mm, 70 mm deep"),
    "banana": (0.20, 0.04, 0.04, 0.2, "banana: ≈ 20 cm long, Ø 3.5–4 cm"),
    "apple": (0.08, 0.08, 0.08, 0.15, "apple: Ø 70–85 mm"),
    "orange": (0.08, 0.08, 0.08, 0.15, "orange: Ø 70–85 mm"),
    "sandwich": (0.12, 0.10, 0.05, 0.3, "sandwich of two bread slices"),
    "broccoli": (0.12, 0.12, 0.14, 0.3, "broccoli head"),
    "carrot": (0.18, 0.03, 0.03, 0.3, "carrot: 15–20 cm long, Ø 3 cm"),
    "hot_dog": (0.16, 0.04, 0.04, 0.2, "hot dog in a bun"),
    "pizza": (0.30, 0.30, 0.02, 0.3, "12 in pizza"),
    "donut": (0.10, 0.10, 0.035, 0.2, "ring doughnut: Ø 90–100 mm"),
    "cake": (0.20, 0.20, 0.10, 0.3, "8 in round cake"),
    "chair": (0.60, 0.60, 0.95, 0.2,
              "office chair (EN 1335 / BIFMA X5.1): seat 45–50 cm wide, 0.9–1.0 m tall"),
    "couch": (2.00, 0.90, 0.85, 0.25, "three-seat sofa: 2.0 × 0.9 m, 0.85 m tall"),
    "potted_plant": (0.30, 0.30, 0.50, 0.4, "indoor potted plant, pot Ø 20–30 cm"),
    "bed": (1.60, 2.10, 0.50, 0.2, "double bed: 1.4–1.6 × 2.0 m mattress, frame"),
    "dining_table": (1.60, 0.90, 0.75, 0.25,
                     "four-seat table: 1.6 × 0.9 m, height 0.72–0.76 m (EN 1730)"),
    "toilet": (0.38, 0.70, 0.80, 0.15, "close-coupled WC with cistern"),
    "tv": (0.55, 0.20, 0.45, 0.3,
           "24 in 16:9 monitor (screen 53 × 30 cm) on its stand, ≈ 45 cm tall, 20 cm deep"),
    "laptop": (0.33, 0.23, 0.22, 0.15, "14 in laptop, open: 33 × 23 cm base, lid ≈ 22 cm"),
    "mouse": (0.11, 0.06, 0.038, 0.15, "desktop mouse: ≈ 110 × 60 × 38 mm"),
    "remote": (0.18, 0.045, 0.02, 0.2, "TV remote: ≈ 180 × 45 × 20 mm"),
    "keyboard": (0.44, 0.135, 0.03, 0.15,
                 "full-size 104/105-key keyboard (ISO/IEC 9995, 19.05 mm key pitch): 44 × 13.5 × 3 cm"),
    "cell_phone": (0.147, 0.072, 0.008, 0.1, "6.1 in smartphone: 147 × 72 × 8 mm"),
    "microwave": (0.48, 0.36, 0.28, 0.15, "20 l countertop microwave"),
    "oven": (0.60, 0.60, 0.90, 0.1, "free-standing cooker, 600 mm kitchen module"),
    "toaster": (0.28, 0.17, 0.19, 0.15, "two-slot toaster"),
    "sink": (0.50, 0.40, 0.20, 0.2, "kitchen sink bowl"),
    "refrigerator": (0.60, 0.65, 1.80, 0.15, "fridge-freezer, 600 mm kitchen module"),
    "book": (0.152, 0.229, 0.025, 0.3, "trade paperback 6 × 9 in, 2.5 cm thick"),
    "clock": (0.30, 0.05, 0.30, 0.2, "wall clock: Ø 30 cm"),
    "vase": (0.12, 0.12, 0.25, 0.3, "flower vase: Ø 12 cm, 25 cm tall"),
    "scissors": (0.20, 0.08, 0.015, 0.2, "office scissors: 8 in"),
    "teddy_bear": (0.25, 0.20, 0.35, 0.4, "sitting teddy bear, ≈ 35 cm"),
    "hair_drier": (0.25, 0.09, 0.25, 0.2, "hand-held hair dryer"),
    "toothbrush": (0.19, 0.02, 0.02, 0.1, "manual toothbrush: 190 mm long"),
}

#: label → ClassPrior (semi-axes = half the dimensions of ``_TABLE``).
BUILTIN_CLASSES = {
    label: ClassPrior(np.array([w / 2, d / 2, h / 2]), spread)
    for label, (w, d, h, spread, _) in _TABLE.items()
}
#: label → where its numbers come from.
CLASS_SOURCES = {label: row[-1] for label, row in _TABLE.items()}


def builtin_class_prior(label: str) -> ClassPrior | None:
    """The built-in prior of a COCO-80 label (YOLO's names, ``_`` for spaces), or None."""
    return BUILTIN_CLASSES.get(str(label))


def class_prior(priors, label: str) -> ClassPrior | None:
    """The ``ClassPrior`` of ``label`` under a sequence's ``priors`` (``Priors.class_prior``:
    its own entry, else the built-in table's unless ``builtin_classes`` is off); without
    priors, the built-in table's."""
    return builtin_class_prior(label) if priors is None else priors.class_prior(label)
