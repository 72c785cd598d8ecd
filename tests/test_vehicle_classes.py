"""One vehicle-class list: every per-class table and every shipped file uses its names."""
from __future__ import annotations

import gzip
import json

import pytest

from adv3d_runner.vehicle_classes import (
    TYPICAL_DIMENSIONS,
    VEHICLE_CLASSES,
    is_class_name,
    plausibility_warning,
    unknown_classes,
)


def test_list_is_unique_and_well_formed():
    assert len(set(VEHICLE_CLASSES)) == len(VEHICLE_CLASSES)
    assert all(is_class_name(c) for c in VEHICLE_CLASSES)
    assert "other" in VEHICLE_CLASSES
    assert not is_class_name("Sedan!") and not is_class_name("") and not is_class_name(3)
    assert is_class_name("tractor")  # files may use classes the tools do not know


def test_per_class_tables_use_the_list():
    from adv3d_runner.scene.actors import CLASS_FALLBACK
    from adv3d_runner.scene.commonroad import CLASS_HEIGHT
    from adv3d_runner.scene.generate import CLASSES

    assert unknown_classes(CLASSES) == []
    assert unknown_classes(CLASS_HEIGHT) == []
    assert unknown_classes(TYPICAL_DIMENSIONS) == []
    assert unknown_classes(CLASS_FALLBACK) == []
    assert unknown_classes(c for alts in CLASS_FALLBACK.values() for c in alts) == []
    assert unknown_classes(["sedan", "tractor"]) == ["tractor"]


def test_every_class_in_the_shipped_files_is_known(repo_root):
    library = json.loads((repo_root / "assets" / "vehicles" / "library.json").read_text())
    found = {a["class"] for a in library["assets"]}
    scenes = sorted((repo_root / "scenes").rglob("*.json*"))
    assert scenes
    for path in scenes:
        raw = path.read_bytes()
        doc = json.loads(gzip.decompress(raw) if path.suffix == ".gz" else raw)
        if isinstance(doc, dict) and doc.get("format") == "adv3d-scene":
            found |= {a["class"] for a in doc["actors"]}
    assert found and unknown_classes(sorted(found)) == []


def test_plausibility_warning():
    assert plausibility_warning("sedan", (4.6, 1.8, 1.45)) is None
    assert plausibility_warning("tractor", (9.0, 9.0, 9.0)) is None
    w = plausibility_warning("sedan", (2.55, 1.5, 1.3), hint="consider Real length")
    assert w is not None and w.startswith("sedan of 2.55 x 1.50 x 1.30 m") and w.endswith("consider Real length")


@pytest.mark.blender
def test_addon_class_menu_is_the_list():
    pytest.importorskip("bpy")
    from blender_addon import props

    assert props.VEHICLE_CLASSES is VEHICLE_CLASSES
