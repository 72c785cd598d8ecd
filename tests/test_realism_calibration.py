"""Realism on any vehicle mesh and its calibration (adv3d_runner/shapes/realism.py,
realism_calibration.py; docs/realism.md, "Calibration").

Fast tests generate their hard cases and unrealistic shapes here; the slow one runs the report on
the TORCS cars of Debian's torcs-data when they are unpacked (ADV3D_TORCS_CARS)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from adv3d_runner.shapes import realism as R
from adv3d_runner.shapes import realism_calibration as C
from adv3d_runner.shapes.shape_space import ShapeSpace

DATA = Path(__file__).parent / "data" / "ac3d_box_car.acc"
TORCS_CARS = Path(os.environ.get("ADV3D_TORCS_CARS", "/tmp/torcs/x/usr/share/games/torcs/cars"))


@pytest.fixture(scope="module")
def space():
    return ShapeSpace.load()


@pytest.fixture(scope="module")
def ref(space):
    return R.default_reference(space)


def rounded_car(length=4.6, width=1.8, height=1.45):
    """A sedan-like solid: a rounded lower body and a cabin (two superellipsoid-ish boxes)."""
    body = trimesh.creation.box(extents=[length, width, 0.55 * height])
    body.apply_translation([0, 0, 0.2 + 0.275 * height])
    cabin = trimesh.creation.box(extents=[0.5 * length, 0.9 * width, 0.45 * height])
    cabin.apply_translation([-0.05 * length, 0, 0.2 + 0.55 * height + 0.225 * height - 0.2])
    wheels = []
    for x in (-0.32 * length, 0.32 * length):
        for y in (-0.4 * width, 0.4 * width):
            w = trimesh.creation.cylinder(radius=0.32, height=0.22, sections=16)
            w.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
            w.apply_translation([x, y, 0.32])
            wheels.append(w)
    return C._grounded(trimesh.util.concatenate([body, cabin, *wheels]))


def test_body_dimensions_leave_out_mirrors_and_antennas():
    car = rounded_car()
    v, f = np.asarray(car.vertices), np.asarray(car.faces)
    plain = R.body_dimensions(v, f)
    mirrored = C.with_mirrors(car)
    antenna = trimesh.creation.box(extents=[0.02, 0.02, 0.6])
    antenna.apply_translation([-0.5, 0.3, car.vertices[:, 2].max() + 0.3])
    both = trimesh.util.concatenate([mirrored, antenna])
    got = R.body_dimensions(np.asarray(both.vertices), np.asarray(both.faces))
    assert R.mesh_dimensions(both.vertices)[1] > plain[1] + 0.15  # the box has the mirrors
    assert R.mesh_dimensions(both.vertices)[2] > plain[2] + 0.5  # and the antenna
    assert np.allclose(got, plain, atol=0.02)
    assert np.allclose(plain, R.mesh_dimensions(v), atol=0.02)  # a plain body: its box


def test_mesh_report_keeps_the_body_and_reports_what_the_grid_drops(space, ref):
    car = C.with_double_walls(C.with_interior(C.with_mirrors(rounded_car())))
    rep = R.mesh_realism_report(space, np.asarray(car.vertices), np.asarray(car.faces), ref, vehicle_class="sedan")
    voxel = space.grid.voxel * space.grid.extent_m
    # no solid outside the body: every decoded point within a voxel of the source surface
    assert rep["outside_source_m"][0] < voxel
    # no hollow or doubled panels: one closed part, no cavity, genus 0
    assert rep["cavities"] == 0 and rep["genus_robust"] == 0
    assert rep["floating_volume_fraction"] <= R.LIMITS.floating_volume_max
    # the 2 cm mirrors: kept (decoded as wide as the source) or reported as dropped width
    src_w, dec_w = rep["source_dimensions_m"][1], rep["dimensions_m"][1]
    assert rep["dropped_extent_m"][1] == pytest.approx(max(0.0, src_w - dec_w))
    assert dec_w > src_w - 0.05 or rep["dropped_extent_m"][1] > 0.3
    # dimensions are the body's, without the mirrors
    assert rep["body_dimensions_m"][1] == pytest.approx(1.8, abs=0.1)
    assert rep["limits"] == R.LIMITS.resolve(ref, voxel)
    assert set(rep["flags"]) == set(R.check_flags(rep, rep["limits"]))


def test_double_walls_with_open_windows_decode_solid(space, ref):
    """The held-out CAD's hollow bodies: an inner skin 3 cm inside the outer one and the side
    windows open. The inner skin, seen from outside only through the windows, leaves the sign."""
    from adv3d_runner.shapes.decode import extract_surface
    from adv3d_runner.shapes.library import load_asset_mesh, load_library
    from adv3d_runner.shapes.sdf import sdf_volume

    car = C.with_open_windows(C.with_double_walls(load_asset_mesh(load_library(), "kenney-car-kit.sedan")))
    v, f = np.asarray(car.vertices), np.asarray(car.faces)
    rep = R.mesh_realism_report(space, v, f, ref, vehicle_class="sedan")
    voxel = space.grid.voxel * space.grid.extent_m
    assert rep["floating_volume_fraction"] == 0.0 and rep["cavities"] == 0
    assert rep["thinnest_wall_m"] >= voxel and rep["thin_wall_fraction"] < 0.01
    # without the visibility rule (the shape-space build's SDF) it is a hollow shell
    hollow = sdf_volume(v, f, space.grid, space.method)
    assert R.wall_thickness(hollow, space.grid).mean() < 0.5 * R.wall_thickness(
        sdf_volume(v, f, space.grid, space.method, min_visibility=R.MESH_MIN_VISIBILITY), space.grid).mean()
    extract_surface(hollow, space.grid)  # still a surface, just the wrong one


def test_unrealistic_shapes_fail_the_report(space, ref):
    car = rounded_car()
    rng = np.random.default_rng(0)
    for name, mesh, cls in [("narrow", C.narrow_sedan(car), "sedan"),
                            ("flatbed", C.fused_flatbed(car), "sedan"),
                            ("blob", C.blob(rng, (2.93, 1.31, 0.93)), None)]:
        rep = R.mesh_realism_report(space, np.asarray(mesh.vertices), np.asarray(mesh.faces), ref, vehicle_class=cls)
        assert not rep["realistic"], name
    assert "dimension_excess" in R.mesh_realism_report(
        space, *(np.asarray(x) for x in (C.narrow_sedan(car).vertices, C.narrow_sedan(car).faces)), ref,
        vehicle_class="sedan")["flags"]


def test_confusion_and_proposed_limits_on_synthetic_records():
    def rec(name, kind, **fig):
        base = {"jsd": 0.5, "nearest_chamfer_m": 0.1, "mahalanobis": 1.0, "floating_volume_fraction": 0.0,
                "genus_robust": 0, "thinnest_wall_m": 0.2, "dimension_excess": [0.0, 0.0, 0.0]}
        base.update(fig)
        return {"name": name, "kind": kind, "report": base}

    limits = {"jsd": 0.55, "nearest_chamfer_m": 0.156, "mahalanobis": 4.0, "floating_volume_fraction": 1e-3,
              "genus_robust": 0, "thinnest_wall_m": 0.096, "dimension_excess": 0.0}
    records = [rec("a", "real"), rec("b", "real", thinnest_wall_m=0.05), rec("c", "real", jsd=0.56),
               rec("x", "unrealistic", jsd=0.7), rec("y", "unrealistic", dimension_excess=[0, 0.2, 0]),
               {"name": "z", "kind": "unrealistic", "error": "no surface"}]
    t = C.confusion(records, limits)
    assert (t["real"]["pass"], t["real"]["n"]) == (1, 3)
    assert (t["unrealistic"]["fail"], t["unrealistic"]["n"]) == (3, 3)
    assert t["flags"]["b"] == ["thinnest_wall_m"] and t["flags"]["z"] == ["error"]
    assert t["per_check"]["jsd"]["real_pass_rate"] == pytest.approx(2 / 3)
    base = R.RealismLimits(jsd_max=0.55, nearest_chamfer_max_m=0.156, mahalanobis_max=4.0, thinnest_wall_min_m=0.096)
    new = C.propose_limits(records, base, limits)
    assert new.jsd_max == pytest.approx(0.56) and new.thinnest_wall_min_m == pytest.approx(0.05)
    assert new.dimension_excess_max == 0.0 and new.genus_robust_max == 0  # no real genus above 0 here
    t2 = C.confusion(records, new.resolve(None, 0.096))
    assert t2["real"]["pass"] == 3 and t2["unrealistic"]["fail"] == 3


def test_cli_mesh_and_set_reports(tmp_path, capsys):
    from adv3d_runner.cli import main as adv3d_main

    assert adv3d_main(["shapes", "realism", "--mesh", str(DATA), "--class", "sedan", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["source_dimensions_m"] == pytest.approx([4.0, 1.8, 1.5], abs=1e-6)
    assert rep["flags"] == R.check_flags(rep, rep["limits"]) and rep["realistic"] == (not rep["flags"])
    assert rep["dimension_class"] == "sedan" and len(rep["latent"]) == 3
    assert adv3d_main(["shapes", "realism", "--mesh", str(DATA)]) == 0
    text = capsys.readouterr().out
    assert "Jensen-Shannon distance" in text and "decoding lost" in text
    assert adv3d_main(["shapes", "realism", "--set", str(DATA), str(DATA), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_found"] == 2 and 0.0 <= s["cov_cd"] <= 1.0 and s["nna_cd"] >= 0.5


@pytest.mark.slow
@pytest.mark.skipif(not (TORCS_CARS / "p406" / "p406.acc").is_file(),
                    reason="TORCS cars not unpacked (apt-get download torcs-data; dpkg-deb -x; ADV3D_TORCS_CARS)")
def test_torcs_road_cars_pass_the_calibrated_report(space, ref):
    from adv3d_runner.shapes.mesh_io import import_vehicle

    names = ("155-DTM", "acura-nsx-sz", "p406", "car1-stock1", "car1-stock2", "car1-trb1", "car1-trb3",
             "car2-trb1", "car3-trb1", "car4-trb1", "car5-trb1", "car6-trb1", "car7-trb1", "car8-trb1")
    passed = []
    for n in names:
        mesh = import_vehicle(TORCS_CARS / n / f"{n}.acc")[0]
        rep = R.mesh_realism_report(space, np.asarray(mesh.vertices), np.asarray(mesh.faces), ref,
                                    vehicle_class="sports")
        passed.append(rep["realistic"])
    assert np.mean(passed) >= C.TARGET_REAL_PASS - 1 / len(names), passed
