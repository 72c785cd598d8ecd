"""The one list of vehicle classes, shared by the vehicle library, scenes, the generators and the
Blender add-on (pure Python: the add-on imports it in-process).

Files accept any lower-case identifier as a class (:func:`is_class_name`), so a library can hold
e.g. a ``"tractor"`` without a code change; :data:`VEHICLE_CLASSES` is the list the tools know:
the add-on's class menu, the examples in error messages, and the keys that every per-class
table (scene generator, CommonRoad heights, asset fallbacks, typical dimensions) must use.
``"other"`` stands for anything that fits no named class.
"""
from __future__ import annotations

import re

#: Known classes: road cars first (the paper's six shape-space classes), then large vehicles,
#: special road cars, two-wheelers, and ``"other"``. The order is the add-on's menu order.
VEHICLE_CLASSES: tuple[str, ...] = (
    "sedan", "hatchback", "sports", "suv", "van", "pickup", "truck", "bus",
    "ambulance", "fire_truck", "garbage_truck", "police", "taxi", "motorcycle", "other",
)

#: What a class name in a file must look like.
CLASS_PATTERN = re.compile(r"^[a-z][a-z0-9_]*$")

#: Typical real-world (length, width, height) in metres per class: used to warn about
#: implausible sizes on import (docs/library.md). Figures are rounded class medians of current
#: European/US models (e.g. sedan: VW Passat 4.78 x 1.83 x 1.48, Toyota Camry 4.88 x 1.84 x 1.44).
TYPICAL_DIMENSIONS: dict[str, tuple[float, float, float]] = {
    "sedan": (4.7, 1.8, 1.45),
    "hatchback": (4.2, 1.8, 1.45),
    "sports": (4.5, 1.9, 1.3),
    "suv": (4.8, 1.9, 1.75),
    "van": (5.2, 2.0, 2.1),
    "pickup": (5.5, 2.0, 1.85),
    "truck": (7.5, 2.5, 3.2),
    "bus": (12.0, 2.55, 3.2),
    "ambulance": (6.0, 2.1, 2.7),
    "fire_truck": (9.0, 2.5, 3.3),
    "garbage_truck": (9.0, 2.5, 3.5),
}


#: Real (length, width, height) ranges in metres per vehicle class, each (low, high). Widths
#: are body widths without mirrors. Sources (docs/realism.md has the full table):
#:
#: * legal limits: EU Council Directive 96/53/EC, Annex I (width 2.55 m, 2.60 m for
#:   conditioned bodies; height 4.00 m; rigid motor vehicle 12.00 m; bus 13.5 m with two
#:   axles, 15 m with more, articulated 18.75 m); US 23 CFR 658.15 (width 102 in = 2.59 m);
#:   Japanese kei car category (3.40 x 1.48 x 2.00 m), the smallest highway-legal cars;
#: * smallest and largest production examples per class, from the manufacturers' published
#:   dimensions (named in docs/realism.md, e.g. Smart Fortwo 2.69 m long, Lotus Elise 1.12 m
#:   high, Chevrolet Suburban 5.73 x 2.06 m, Mercedes-Benz Sprinter 7.37 m).
DIMENSION_RANGES: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "sedan": ((4.0, 5.4), (1.65, 1.97), (1.35, 1.60)),
    "hatchback": ((2.5, 4.5), (1.47, 1.85), (1.38, 1.80)),
    "sports": ((3.7, 5.1), (1.55, 2.05), (1.00, 1.40)),
    "suv": ((3.4, 5.8), (1.60, 2.10), (1.55, 2.00)),
    "van": ((4.2, 7.4), (1.70, 2.10), (1.70, 3.10)),
    "pickup": ((4.8, 6.8), (1.75, 2.45), (1.65, 2.10)),
    "truck": ((4.7, 12.0), (1.69, 2.55), (2.00, 4.00)),
    "bus": ((6.5, 18.75), (2.00, 2.55), (2.60, 4.00)),
    "ambulance": ((5.2, 7.7), (1.90, 2.55), (2.30, 3.20)),
    "fire_truck": ((6.5, 12.0), (2.20, 2.60), (2.70, 4.00)),
    "garbage_truck": ((6.5, 12.0), (2.30, 2.60), (3.00, 4.00)),
    "police": ((4.4, 5.4), (1.70, 2.05), (1.40, 2.00)),
    "taxi": ((4.2, 5.4), (1.69, 2.05), (1.40, 1.90)),
    # motorcycles: from a 125 cc commuter to a touring bike (manufacturers' published sizes)
    "motorcycle": ((1.7, 2.7), (0.6, 1.05), (1.0, 1.6)),
}


def is_class_name(name: object) -> bool:
    """True for a lower-case identifier (``[a-z][a-z0-9_]*``), the form every file uses."""
    return isinstance(name, str) and CLASS_PATTERN.match(name) is not None


def class_examples(n: int) -> list[str]:
    """The first ``n`` known classes (for "such as ..." in messages)."""
    return list(VEHICLE_CLASSES[:n])


def unknown_classes(names) -> list[str]:
    """The names in ``names`` that are not in :data:`VEHICLE_CLASSES` (for per-class tables)."""
    return [n for n in names if n not in VEHICLE_CLASSES]


def plausibility_warning(vehicle_class: str, dims: tuple[float, float, float],
                         hint: str = "consider --dimensions") -> str | None:
    """A warning when dimensions are more than 30 % off the class's typical size (None when
    plausible or the class has no typical size); ``hint`` says what to do about it."""
    typical = TYPICAL_DIMENSIONS.get(vehicle_class)
    if typical is None:
        return None
    off = [d / t for d, t in zip(dims, typical)]
    if any(r < 0.7 or r > 1.3 for r in off):
        return (f"{vehicle_class} of {dims[0]:.2f} x {dims[1]:.2f} x {dims[2]:.2f} m is far from the typical "
                f"{typical[0]} x {typical[1]} x {typical[2]} m; {hint}")
    return None
