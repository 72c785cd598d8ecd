"""The Blender add-on on the PyPI ``bpy`` module: registration, every operator on fixture data
(written under tmp_path), live sliders, the scene round trip, error reporting, the built zip.

One bpy session for the whole module (importing bpy costs seconds); each test starts from
``read_factory_settings(use_empty=True)`` with the add-on registered.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

CC0 = "Creative Commons Zero v1.0 Universal (CC0) https://creativecommons.org/publicdomain/zero/1.0/\n"


# --------------------------------------------------------------------------- fixtures (data)

def _vehicle_mesh(length: float, width: float, height: float, cabin: float):
    """A box body with a cabin box on top (a crude car), convention frame, trimesh."""
    import trimesh

    body = trimesh.creation.box(extents=(length, width, height * 0.55))
    body.apply_translation((0, 0, height * 0.275))
    top = trimesh.creation.box(extents=(length * cabin, width * 0.85, height * 0.45))
    top.apply_translation((-length * 0.1, 0, height * 0.55 + height * 0.225))
    return trimesh.util.concatenate([body, top])


FIXTURE_CARS = {  # id: (L, W, H, cabin fraction, class)
    "fx.sedan": (4.6, 1.8, 1.45, 0.5, "sedan"),
    "fx.van": (5.2, 2.0, 2.1, 0.8, "van"),
    "fx.suv": (4.7, 1.95, 1.8, 0.6, "suv"),
    "fx.sports": (4.3, 1.85, 1.2, 0.4, "sports"),
}


def make_library(root: Path) -> Path:
    """library.json + glb meshes + licence under ``root`` (through the runner's own API)."""
    from adv3d_runner.shapes.cleaning import clean_mesh
    from adv3d_runner.shapes.library import VehicleAsset, VehicleLibrary, save_library
    from adv3d_runner.shapes.mesh_io import mesh_dimensions, read_library_mesh, write_library_glb

    library = VehicleLibrary(root=root)
    (root / "fx").mkdir(parents=True, exist_ok=True)
    (root / "fx" / "License.txt").write_text(CC0)
    for asset_id, (L, W, H, cab, cls) in FIXTURE_CARS.items():
        mesh, report = clean_mesh(_vehicle_mesh(L, W, H, cab))
        rel = f"fx/{asset_id.split('.')[1]}.glb"
        write_library_glb(mesh, root / rel)
        stored = read_library_mesh(root / rel)
        library.put(VehicleAsset(
            id=asset_id, file=rel, vehicle_class=cls, dimensions=tuple(round(v, 4) for v in mesh_dimensions(stored)),
            source={"pack": "fx", "file": f"{asset_id}.glb"}, licence={"name": "CC0-1.0", "file": "fx/License.txt"},
            triangle_count=len(stored.faces), cleaning=report, curation={"note": "test fixture"}))
    return save_library(library, root / "library.json")


def make_space(path: Path, resolution: int = 32) -> Path:
    """A shape space over analytic box SDFs of the fixture cars (no mesh SDF needed: fast)."""
    from adv3d_runner.shapes.sdf import grid_for_dimensions
    from adv3d_runner.shapes.shape_space import shape_space_from_sdfs

    dims = [v[:3] for v in FIXTURE_CARS.values()]
    grid = grid_for_dimensions(dims, resolution)
    p = grid.points()
    sdfs = []
    for L, W, H, cab, _ in FIXTURE_CARS.values():
        def box(centre, half):
            q = np.abs(p - centre) - half
            return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        e = grid.extent_m
        g = grid.ground_z
        body = box(np.array([0, 0, g + 0.275 * H / e]), np.array([L, W, 0.55 * H]) / (2 * e))
        top = box(np.array([-0.1 * L / e, 0, g + 0.775 * H / e]), np.array([L * cab, 0.85 * W, 0.45 * H]) / (2 * e))
        sdf = np.clip(np.minimum(body, top), -grid.truncation, grid.truncation)
        sdfs.append(sdf.reshape(resolution, resolution, resolution))
    space = shape_space_from_sdfs(np.stack(sdfs), list(FIXTURE_CARS), grid, k=3)
    return space.save(path)


def make_scene(path: Path, frames: int = 40) -> Path:
    """A two-lane scene in a large (UTM-like) map frame, an actor with a gap, one with speeds."""
    from adv3d_runner.scene.schema import (
        Actor, Background, Ego, Lane, Scene, Source, Track, default_sensors, save_scene)

    t = np.arange(frames) * 0.1
    ego = Ego(dimensions=[4.6, 1.9, 1.6], wheelbase=2.8,
              track=Track(x=351234.5 + 10 * t, y=5612345.25 + 0 * t, yaw=0 * t, speed=10 + 0 * t),
              sensors=default_sensors())
    lanes = [Lane(0, np.array([[351200, 5612345.25], [351600, 5612345.25]]), 3.5, left=1),
             Lane(1, np.array([[351200, 5612348.75], [351600, 5612348.75]]), 3.5, right=0)]
    n = frames - 10
    valid = np.ones(n, bool)
    valid[5:8] = False
    actors = [
        Actor(3, "sedan", [4.5, 1.8, 1.5], Track(x=351250 + 8 * t[:n], y=5612348.75 + 0.01 * np.sin(t[:n]),
                                                  yaw=3.1415 + 0.001 * t[:n], start=10, valid=valid)),
        Actor(7, "truck", [8, 2.5, 3.2], Track(x=351270 - 5 * t, y=5612345.25 + 0 * t, yaw=-3.14159 + 0 * t,
                                               speed=5 + 0 * t)),
    ]
    scene = Scene("fixture-scene", Source("generated", {"seed": 1}), 0.1, frames, lanes, Background(), ego, actors)
    save_scene(scene, path)
    return path


@pytest.fixture
def ctx(addon):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context


@pytest.fixture(scope="module")
def data(tmp_path_factory, addon):
    root = tmp_path_factory.mktemp("adv3d_blender")
    lib = make_library(root / "library")
    space = make_space(root / "space.npz")
    scene = make_scene(root / "scene.json")
    return {"root": root, "library": lib, "space": space, "scene": scene}


@pytest.fixture
def lib_copy(data, tmp_path) -> Path:
    shutil.copytree(data["library"].parent, tmp_path / "library")
    return tmp_path / "library" / "library.json"


# --------------------------------------------------------------------------- registration

def test_register_unregister_twice(addon):
    addon.unregister()
    assert not hasattr(bpy.types.Scene, "adv3d")
    assert not hasattr(bpy.types, "ADV3D_PT_library")
    for _ in range(2):
        addon.register()
        assert hasattr(bpy.types.Scene, "adv3d") and hasattr(bpy.types.Object, "adv3d")
        for panel in ("ADV3D_PT_library", "ADV3D_PT_shapes", "ADV3D_PT_scenes", "ADV3D_PT_review"):
            cls = getattr(bpy.types, panel)
            assert cls.bl_category == "Adv3D" and cls.bl_region_type == "UI"
        addon.unregister()
        assert not hasattr(bpy.types.Scene, "adv3d")
        assert not hasattr(bpy.types, "ADV3D_OT_scene_load")
    addon.register()  # leave it registered for the module's other tests


def test_addon_sources_never_import_torch(repo_root):
    import re

    for path in (repo_root / "blender_addon").glob("*.py"):
        assert not re.search(r"(?m)^\s*(import torch|from torch\b)", path.read_text()), path


def test_set_mesh_arrays_in_place_and_rebuild(ctx):
    from blender_addon import meshdata

    v, f = meshdata.box_arrays(4.0, 2.0, 1.5)
    obj = meshdata.new_mesh_object("m", v, f)
    assert meshdata.set_mesh_arrays(obj.data, v * 2.0, f) is False  # same topology: positions only
    got_v, got_f = meshdata.mesh_arrays(obj.data)
    np.testing.assert_allclose(got_v, v * 2.0, atol=1e-6)
    np.testing.assert_array_equal(got_f, f)
    assert meshdata.set_mesh_arrays(obj.data, v[:4], f[:2]) is True  # fewer faces: rebuilt
    assert (len(obj.data.vertices), len(obj.data.polygons), len(obj.data.loops)) == (4, 2, 6)
    assert not obj.data.validate()  # nothing to fix
    with pytest.raises(ValueError):
        meshdata.set_mesh_arrays(obj.data, v[:3], f)


# --------------------------------------------------------------------------- library

def test_library_load_edit_save_keeps_other_fields(ctx, lib_copy):
    from adv3d_runner.shapes.library import load_library

    before = load_library(lib_copy)
    assert bpy.ops.adv3d.library_load(filepath=str(lib_copy)) == {"FINISHED"}
    lib = ctx.scene.adv3d.library
    assert [a.asset_id for a in lib.assets] == before.ids()
    assert "triangles" in lib.assets[0].cleaning_report
    lib.assets[1].vehicle_class = "truck"
    lib.assets[2].in_shape_space = False
    assert bpy.ops.adv3d.library_save() == {"FINISHED"}
    after = load_library(lib_copy)
    assert after.assets[1].vehicle_class == "truck"
    assert after.assets[2].in_shape_space is False
    for a, b in zip(before.assets, after.assets):  # everything else unchanged
        ja, jb = a.to_json(), b.to_json()
        ja.pop("class"), jb.pop("class"), ja.pop("in_shape_space"), jb.pop("in_shape_space")
        assert ja == jb


def test_library_import_through_blender(ctx, lib_copy, tmp_path):
    import trimesh

    from adv3d_runner.shapes.library import load_library

    src = tmp_path / "src" / "mypack"
    src.mkdir(parents=True)
    (src / "LICENSE.txt").write_text(CC0)
    mesh = _vehicle_mesh(3.0, 1.4, 1.2, 0.5)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 0, 1)))  # front along +y
    # OBJ files are Y up (Blender's OBJ importer maps file (x, y, z) to Blender (x, -z, y)).
    mesh.vertices = np.asarray(mesh.vertices) @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T
    mesh.export(src / "Little Car.obj")  # front along -z of the file, y up
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    lib = ctx.scene.adv3d.library
    # Up: Auto (OBJ is y up, as Blender's OBJ importer assumes); Front: the file's -Z axis
    assert bpy.ops.adv3d.library_import(filepath=str(src / "Little Car.obj"), vehicle_class="hatchback",
                                        axis_forward="NEGATIVE_Z", length=3.9) == {"FINISHED"}
    library = load_library(lib_copy)
    asset = library.get("mypack.little-car")
    L, W, H = asset.dimensions
    assert L == pytest.approx(3.9, abs=2e-3)  # scaled to the real length, front turned to +x
    assert W == pytest.approx(1.4 * 3.9 / 3.0, abs=5e-3) and H == pytest.approx(1.2 * 3.9 / 3.0, abs=5e-3)
    assert asset.vehicle_class == "hatchback" and asset.licence["name"] == "CC0-1.0"
    assert (lib_copy.parent / asset.file).is_file() and asset.cleaning["triangles"] == asset.triangle_count
    assert lib.assets[lib.active_index].asset_id == asset.id


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb"])
def test_import_axis_options(ctx, lib_copy, tmp_path, suffix):
    """A file in adv3d's own frame (z up, +x front) imports upright with Up Z / Front X; an OBJ
    read with OBJ's default y-up lands on its side (what the Up option is for); glTF is y up by
    the standard, so a .glb comes in upright with Auto."""
    from adv3d_runner.shapes.library import load_library

    src = tmp_path / "zup"
    src.mkdir()
    (src / "License.txt").write_text(CC0)
    mesh = _vehicle_mesh(4.4, 1.8, 1.4, 0.5)
    if suffix == ".glb":
        from adv3d_runner.shapes.mesh_io import write_mesh  # writes glTF's y-up frame

        write_mesh(mesh, src / f"car{suffix}")
    else:
        mesh.export(src / f"car{suffix}")
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    up = "AUTO" if suffix == ".glb" else "Z"
    assert bpy.ops.adv3d.library_import(filepath=str(src / f"car{suffix}"), axis_up=up, axis_forward="X",
                                        asset_id="zup.car") == {"FINISHED"}
    assert load_library(lib_copy).get("zup.car").dimensions == pytest.approx((4.4, 1.8, 1.4), abs=2e-3)
    if suffix == ".obj":  # Auto = y up for OBJ: this z-up file lies on its side
        bpy.ops.adv3d.library_import(filepath=str(src / f"car{suffix}"), asset_id="zup.side")
        L, W, H = load_library(lib_copy).get("zup.side").dimensions
        assert H == pytest.approx(1.8, abs=2e-3)  # the width stands up


def test_export_keeps_the_chosen_format(ctx, data, tmp_path):
    """The file browser's extension check keeps a typed known extension (selecting its format)
    and adds the chosen format's extension to a bare name; .json.gz is one extension."""
    from blender_addon.ops_scene import ADV3D_OT_scene_export
    from blender_addon.ops_shapes import ADV3D_OT_shapes_export

    assert ADV3D_OT_shapes_export.format_of("car.OBJ") == "OBJ"
    assert ADV3D_OT_scene_export.format_of("a.json.gz") == "JSON_GZ"
    assert ADV3D_OT_scene_export.format_of("a.json") == "JSON"
    assert ADV3D_OT_scene_export.format_of("a.gz") is None
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    out = tmp_path / "edited.json.gz"
    assert bpy.ops.adv3d.scene_export(filepath=str(out)) == {"FINISHED"}
    import gzip

    assert gzip.decompress(out.read_bytes()) == Path(data["scene"]).read_bytes()
    # a bare name gets the chosen format's extension
    assert bpy.ops.adv3d.scene_export(filepath=str(tmp_path / "bare"), file_format="JSON_GZ") == {"FINISHED"}
    assert (tmp_path / "bare.json.gz").is_file()
    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    assert bpy.ops.adv3d.shapes_export(filepath=str(tmp_path / "car"), file_format="STL") == {"FINISHED"}
    assert (tmp_path / "car.stl").is_file()


@pytest.mark.parametrize("target", ["folder", "missing_dir", "readonly"])
def test_export_errors_are_reports(ctx, data, tmp_path, target):
    """A folder, a missing folder or an unwritable file: one reported line, no traceback."""
    import os

    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    if target == "folder":
        path = tmp_path / "adir.json"
        path.mkdir()
        path.with_suffix(".glb").mkdir()
    elif target == "missing_dir":
        path = tmp_path / "no" / "such" / "x.json"
    elif os.geteuid() == 0:  # root may write anywhere on disk, but not into /proc
        path = Path("/proc/adv3d-export-test.json")
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        path = ro / "x.json"
        os.chmod(ro, 0o555)
    for op, p in ((bpy.ops.adv3d.scene_export, path), (bpy.ops.adv3d.shapes_export, path.with_suffix(".glb"))):
        with pytest.raises(RuntimeError) as info:
            op(filepath=str(p))
        assert "Traceback" not in str(info.value) and "internal error" not in str(info.value)
    with pytest.raises(RuntimeError, match="choose a file name"):
        bpy.ops.adv3d.scene_export(filepath=str(tmp_path) + "/")


def test_menus_and_preferences(ctx, data, tmp_path, addon):
    """File > Import / Export list the add-on's entries; the preferences' default paths are used
    when a panel has none."""
    from blender_addon import prefs

    assert addon.menu_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    assert addon.menu_export in bpy.types.TOPBAR_MT_file_export._dyn_ui_initialize()
    entry = bpy.context.preferences.addons.get(prefs.PACKAGE) or bpy.context.preferences.addons.new()
    entry.module = prefs.PACKAGE
    try:
        p = prefs.get()
        p.default_space = str(data["space"])
        p.runner = "/usr/bin/python3"
        assert prefs.runner_command() == ["/usr/bin/python3", "-m", "adv3d_runner.cli"]
        assert bpy.ops.adv3d.shapes_load() == {"FINISHED"}  # no path in the panel: the default
        assert ctx.scene.adv3d.shapes.space_path == str(data["space"])
    finally:
        bpy.context.preferences.addons.remove(entry)


def test_panels_have_their_own_collections_and_places(ctx, data, lib_copy):
    """Library row, shape preview and scene each in their own collection, parented to a place,
    and no two places' content overlap."""
    from blender_addon import places

    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    bpy.ops.adv3d.library_show(asset_id="fx.van")
    bpy.ops.adv3d.library_show(asset_id="fx.sedan")
    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    boxes = {}
    for name in ("Adv3D Library", "Adv3D Shape preview", "Adv3D Scene"):
        coll = bpy.data.collections[name]
        place = places.place_of(coll)
        assert place is not None and place.name in coll.objects
        for obj in coll.all_objects:
            assert obj is place or obj.parent is not None  # everything hangs off the place
        boxes[name] = places._world_bounds(place)
    names = list(boxes)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ba, bb = boxes[a], boxes[b]
            apart = ba[2] <= bb[0] or bb[2] <= ba[0] or ba[3] <= bb[1] or bb[3] <= ba[1]
            assert apart, (a, b, ba, bb)
    van, sedan = bpy.data.objects["fx.van"], bpy.data.objects["fx.sedan"]
    assert sedan.matrix_world.translation.x > van.matrix_world.translation.x + 4.0  # side by side


def test_library_rescale_and_turn(ctx, lib_copy):
    from adv3d_runner.shapes.library import load_library

    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    L0, W0, H0 = load_library(lib_copy).get("fx.sedan").dimensions
    assert bpy.ops.adv3d.library_rescale("EXEC_DEFAULT", asset_id="fx.sedan", length=5.0) == {"FINISHED"}
    L1, W1, H1 = load_library(lib_copy).get("fx.sedan").dimensions
    assert L1 == pytest.approx(5.0, abs=2e-3) and W1 == pytest.approx(W0 * 5.0 / L0, abs=2e-3)
    assert bpy.ops.adv3d.library_turn("EXEC_DEFAULT", asset_id="fx.sedan", angle="90") == {"FINISHED"}
    L2, W2, _ = load_library(lib_copy).get("fx.sedan").dimensions
    assert (L2, W2) == pytest.approx((W1, L1), abs=2e-3)
    assert bpy.ops.adv3d.library_turn("EXEC_DEFAULT", asset_id="fx.sedan", angle="-90") == {"FINISHED"}
    bpy.ops.adv3d.library_rescale("EXEC_DEFAULT", asset_id="fx.sedan", length=4.0, width=2.0, height=1.5)
    assert load_library(lib_copy).get("fx.sedan").dimensions == pytest.approx((4.0, 2.0, 1.5), abs=2e-3)


def test_library_show_creates_object(ctx, lib_copy):
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    assert bpy.ops.adv3d.library_show(asset_id="fx.van") == {"FINISHED"}
    obj = ctx.view_layer.objects.active
    assert obj.adv3d.role == "ASSET" and obj.adv3d.key == "fx.van"
    size = np.ptp(np.array([v.co for v in obj.data.vertices]), axis=0)
    assert size == pytest.approx(FIXTURE_CARS["fx.van"][:3], abs=1e-3)


def test_malformed_library_is_reported_not_raised_as_traceback(ctx, tmp_path):
    bad = tmp_path / "library.json"
    bad.write_text(json.dumps({"format": "adv3d-vehicle-library", "version": 1, "assets": [{"id": "x"}]}))
    # bpy.ops turns an operator's ERROR report into RuntimeError carrying the message.
    with pytest.raises(RuntimeError, match=r"\$\.assets\[0\]"):
        bpy.ops.adv3d.library_load(filepath=str(bad))
    assert len(ctx.scene.adv3d.library.assets) == 0
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(RuntimeError, match="JSON"):
        bpy.ops.adv3d.library_load(filepath=str(tmp_path / "junk.json"))


def test_import_of_corrupt_file_is_reported(ctx, lib_copy, tmp_path):
    src = tmp_path / "bad"
    src.mkdir()
    (src / "License.txt").write_text(CC0)
    (src / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage")
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    with pytest.raises(RuntimeError, match="broken.glb"):
        bpy.ops.adv3d.library_import(filepath=str(src / "broken.glb"))


# --------------------------------------------------------------------------- shape space

def _preview_arrays(scene):
    from blender_addon import meshdata, ops_shapes

    return meshdata.mesh_arrays(ops_shapes.preview_object(scene, create=False).data)


def test_sliders_regenerate_preview(ctx, data):
    assert bpy.ops.adv3d.shapes_load(filepath=str(data["space"])) == {"FINISHED"}
    shapes = ctx.scene.adv3d.shapes
    assert shapes.k == 3 and "z1" in shapes.variance_text
    v0, f0 = _preview_arrays(ctx.scene)
    assert len(v0) > 100 and f0.max() == len(v0) - 1
    shapes.latent[0] = 1.0  # the update callback runs at once in background mode
    v1, f1 = _preview_arrays(ctx.scene)
    assert f1.max() < len(v1)
    assert len(v1) != len(v0) or not np.allclose(v1, v0)
    assert shapes.last_update_ms > 0
    # The width scale widens the car and keeps it on the ground.
    shapes.width_scale = 0.0
    narrow = np.ptp(_preview_arrays(ctx.scene)[0][:, 1])
    shapes.width_scale = 1.0
    wide_v = _preview_arrays(ctx.scene)[0]
    assert np.ptp(wide_v[:, 1]) > narrow * 1.4
    assert wide_v[:, 2].min() == pytest.approx(0.0, abs=1e-4)
    # Decode agrees with the runner for the same unit vector.
    from adv3d_runner.shapes.shape_space import ShapeSpace

    ref_v, ref_f = ShapeSpace.load(data["space"]).decode_arrays(
        [shapes.latent[0], shapes.latent[1], shapes.latent[2], shapes.width_scale, shapes.length_scale])
    assert len(ref_v) == len(wide_v)
    np.testing.assert_allclose(wide_v, ref_v, atol=1e-5)


def test_whole_vector_assignment_updates_once(ctx, data, monkeypatch):
    from blender_addon import ops_shapes

    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    calls = []
    original = ops_shapes.update_preview
    monkeypatch.setattr(ops_shapes, "update_preview", lambda scene: calls.append(1) or original(scene))
    ctx.scene.adv3d.shapes.latent = [0.2] * len(ctx.scene.adv3d.shapes.latent)
    assert len(calls) == 1
    ops_shapes.set_unit(ctx.scene.adv3d.shapes, np.array([0.1, 0.2, 0.3, 0.4, 0.5]))
    assert len(calls) == 1  # bulk set is silent; the operator refreshes once afterwards


def test_random_sample_is_seeded(ctx, data):
    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    shapes = ctx.scene.adv3d.shapes
    shapes.seed = 7
    bpy.ops.adv3d.shapes_random()
    first = list(shapes.latent[:3]) + [shapes.width_scale, shapes.length_scale]
    v_first = _preview_arrays(ctx.scene)[0]
    assert shapes.seed == 8
    expected = np.random.default_rng(7).random(5)
    np.testing.assert_allclose(first, expected, atol=1e-6)
    bpy.ops.adv3d.shapes_random()
    assert not np.allclose(list(shapes.latent[:3]), first[:3])
    shapes.seed = 7
    bpy.ops.adv3d.shapes_random()
    np.testing.assert_allclose(_preview_arrays(ctx.scene)[0], v_first)


def test_nearest_asset_and_export(ctx, data, tmp_path):
    import trimesh

    from adv3d_runner.shapes.shape_space import ShapeSpace

    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    space = ShapeSpace.load(data["space"])
    from blender_addon import ops_shapes

    ops_shapes.set_unit(ctx.scene.adv3d.shapes, space.asset_unit("fx.van"))
    assert bpy.ops.adv3d.shapes_nearest() == {"FINISHED"}
    assert ctx.scene.adv3d.shapes.nearest_asset == "fx.van"
    out = tmp_path / "shape.ply"
    assert bpy.ops.adv3d.shapes_export(filepath=str(out)) == {"FINISHED"}
    mesh = trimesh.load(out, process=False)
    v, f = space.decode_arrays(space.asset_unit("fx.van"))
    assert len(mesh.faces) == len(f) and mesh.is_watertight
    with pytest.raises(RuntimeError, match="must end in one of"):
        bpy.ops.adv3d.shapes_export(filepath=str(tmp_path / "shape.xyz"))


def test_live_realism_of_the_slider_shape(ctx, data):
    """The Shape space panel measures the preview's realism at every slider change (JSD,
    Mahalanobis, dimensions against the chosen class) with the same numbers as the runner, and
    the full report on demand; the reference of a custom space is built from the library."""
    from adv3d_runner.shapes import realism
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.shapes.shape_space import ShapeSpace
    from blender_addon import ops_shapes

    from blender_addon import runner

    ctx.scene.adv3d.library.path = str(data["library"])
    assert bpy.ops.adv3d.shapes_load(filepath=str(data["space"])) == {"FINISHED"}
    shapes = ctx.scene.adv3d.shapes
    space = ShapeSpace.load(data["space"])
    ref = realism.build_reference(load_library(data["library"]), space)
    runner.realism_reference(runner.load_space(data["space"]), data["library"], wait=True)
    ops_shapes.set_unit(shapes, space.asset_unit("fx.van"))
    shapes.realism_class = "van"                      # the update runs at once in background mode
    u = ops_shapes.current_unit(shapes)
    v, f = space.decode_arrays(u)
    q = realism.quick_measures(v, f, ref, latent=space.unit_to_latent(u)[0], latents=space.latents,
                               vehicle_class="van", chamfer=False)
    live = shapes.realism_live.splitlines()
    assert live[0].startswith(f"JSD {q['jsd']:.3f}") and f"Mahalanobis {q['mahalanobis']:.2f}" in live[1]
    assert "vs real van" in live[2] and shapes.realism_ms > 0
    shapes.latent[0] = 1.0 - shapes.latent[0]         # another shape: new figures
    assert shapes.realism_live.splitlines() != live
    assert bpy.ops.adv3d.shapes_realism() == {"FINISHED"}
    full = realism.realism_report(space, ops_shapes.current_unit(shapes), ref, vehicle_class="van")
    assert shapes.realism_full.splitlines()[0].startswith(f"JSD {full['jsd']:.3f}, nearest {full['nearest_asset']}")
    shapes.latent[1] = 0.3
    assert shapes.realism_full == ""                  # the full report described the previous shape
    shapes.show_realism = False
    shapes.realism_live = ""
    shapes.latent[1] = 0.4
    assert shapes.realism_live == ""


def test_missing_or_corrupt_shape_space_is_reported(ctx, tmp_path):
    with pytest.raises(RuntimeError, match="not found|existing"):
        bpy.ops.adv3d.shapes_load(filepath=str(tmp_path / "none.npz"))
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(RuntimeError, match="bad.npz"):
        bpy.ops.adv3d.shapes_load(filepath=str(tmp_path / "bad.npz"))


def test_build_shape_space_operator(ctx, lib_copy, tmp_path):
    from adv3d_runner.shapes.shape_space import ShapeSpace

    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    shapes = ctx.scene.adv3d.shapes
    shapes.space_path = str(tmp_path / "built.npz")
    shapes.build_resolution = 16
    shapes.build_k = 2
    assert bpy.ops.adv3d.shapes_build() == {"FINISHED"}
    space = ShapeSpace.load(tmp_path / "built.npz")
    assert space.k == 2 and sorted(space.asset_ids) == sorted(FIXTURE_CARS)
    assert shapes.k == 2 and len(_preview_arrays(ctx.scene)[0]) > 0


def test_build_job_steps_are_short_and_esc_cancels(ctx, lib_copy, tmp_path):
    """The modal Build's work driven as Blender's timer drives it: progress in the status bar,
    no step near half a second, the same bytes as the runner's one-call build; Esc leaves no
    file behind."""
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.shapes.shape_space import build_shape_space
    from blender_addon import jobs, ops_shapes

    out = tmp_path / "job.npz"
    job = jobs.Job("Build shape space", ops_shapes.build_steps(load_library(lib_copy), str(out),
                                                               {"k": 2, "resolution": 24}))
    texts = []
    while jobs.handle_event(ctx, job, "TIMER", slice_s=0.0) == jobs.RUNNING:
        texts.append(job.status_text())
    assert job.state == jobs.DONE and job.n_steps > 2 * len(FIXTURE_CARS)
    assert job.max_step_s < jobs.MAX_STEP_S
    assert any("SDF 24^3 of fx.van" in t for t in texts) and "Esc" in texts[0]
    ref = build_shape_space(load_library(lib_copy), resolution=24, k=2, progress=False)
    assert out.read_bytes() == ref.to_bytes()
    out.unlink()
    job = jobs.Job("Build shape space", ops_shapes.build_steps(load_library(lib_copy), str(out),
                                                               {"k": 2, "resolution": 24}))
    for _ in range(5):
        jobs.handle_event(ctx, job, "TIMER", slice_s=0.0)
    assert jobs.handle_event(ctx, job, "ESC") == jobs.CANCELLED and not out.exists()
    jobs.show_progress(ctx, None)


# --------------------------------------------------------------------------- scenes

def test_scene_load_creates_objects_and_keyframes(ctx, data):
    from adv3d_runner.scene.schema import load_scene

    assert bpy.ops.adv3d.scene_load(filepath=str(data["scene"])) == {"FINISHED"}
    scene = load_scene(data["scene"])
    objs = {o.name: o for o in bpy.data.objects}
    assert {"ego", "actor 3", "actor 7", "lane 0", "lane 1", "sensor top", "road"} <= set(objs)
    assert ctx.scene.frame_start == 0 and ctx.scene.frame_end == scene.frames - 1
    assert objs["sensor top"].parent == objs["ego"]
    assert objs["sensor top"].location.z == pytest.approx(1.73, abs=1e-6)
    origin = np.asarray(bpy.data.collections["Adv3D Scene"]["adv3d_origin"])
    actor = objs["actor 3"]
    for frame in (12, 20, 29):  # valid frames: pose matches the track
        ctx.scene.frame_set(frame)
        i = frame - 10
        t = scene.actor(3).track
        assert actor.location.x + origin[0] == pytest.approx(t.x[i], abs=2e-3)
        assert actor.location.y + origin[1] == pytest.approx(t.y[i], abs=2e-3)
        assert not actor.hide_render
    for frame in (5, 15, 17):  # before its start, in its gap (track frames 15-17)
        ctx.scene.frame_set(frame)
        assert actor.hide_render and actor.hide_viewport


def test_scene_round_trip_is_identical(ctx, data, tmp_path):
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    out = tmp_path / "exported.json"
    assert bpy.ops.adv3d.scene_export(filepath=str(out)) == {"FINISHED"}
    assert out.read_bytes() == Path(data["scene"]).read_bytes()


def test_scene_edits_are_exported_and_nothing_else(ctx, data, tmp_path):
    from adv3d_runner.scene.schema import load_scene
    from blender_addon import ops_scene

    ctx.scene.adv3d.library.path = str(data["library"])  # the library fx.van is in
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    original = load_scene(data["scene"])
    actor = bpy.data.objects["actor 7"]
    frames = np.arange(original.frames)
    xs = ops_scene.eval_curve(actor, "location", 0, frames)
    xs[20:] += 1.5  # the truck is 1.5 m further ahead from frame 20 on
    ops_scene.set_keys(actor, "location", 0, frames, xs)
    actor.adv3d.asset_id = "fx.van"
    ego = bpy.data.objects["ego"]
    ys = ops_scene.eval_curve(ego, "location", 1, frames)
    ys[30:] += 0.5  # the logged ego drifts left at the end
    ops_scene.set_keys(ego, "location", 1, frames, ys)
    out = tmp_path / "edited.json"
    assert bpy.ops.adv3d.scene_export(filepath=str(out)) == {"FINISHED"}
    edited = load_scene(out)
    a0, a1 = original.actor(7), edited.actor(7)
    np.testing.assert_array_equal(a1.track.x[:20], a0.track.x[:20])
    np.testing.assert_allclose(a1.track.x[20:], a0.track.x[20:] + 1.5, atol=1.5e-3)
    np.testing.assert_array_equal(a1.track.y, a0.track.y)
    assert a1.asset == "fx.van" and a0.asset is None
    assert edited.to_dict()["actors"][0] == original.to_dict()["actors"][0]  # untouched actor
    np.testing.assert_allclose(edited.ego.track.y[30:], original.ego.track.y[30:] + 0.5, atol=1.5e-3)
    np.testing.assert_array_equal(edited.ego.track.y[:30], original.ego.track.y[:30])
    # Speeds re-derived only around the edit.
    np.testing.assert_array_equal(edited.ego.track.speed[:28], original.ego.track.speed[:28])
    assert edited.ego.track.speed[30] > original.ego.track.speed[30]


def test_scene_export_refuses_an_unknown_asset_and_keeps_speeds_of_unmoved_frames(ctx, data, tmp_path):
    """An asset id typed without Apply that the library lacks is refused on export (naming the
    actor and the library); turning the ego's heading moves no position, so its logged speeds
    stay as they are."""
    from adv3d_runner.scene.schema import load_scene, save_scene
    from blender_addon import ops_scene

    logged = load_scene(data["scene"])
    logged.ego.track.speed[:] = 10.5  # a logged speed that positions would not give (10 m/s)
    scene_file = save_scene(logged, tmp_path / "logged.json") or tmp_path / "logged.json"
    bpy.ops.adv3d.scene_load(filepath=str(scene_file))
    actor = bpy.data.objects["actor 7"]
    actor.adv3d.asset_id = "no-such.car"
    with pytest.raises(RuntimeError, match=r"actor 7: asset 'no-such.car' is not in the library"):
        bpy.ops.adv3d.scene_export(filepath=str(tmp_path / "bad.json"))
    assert not (tmp_path / "bad.json").exists()
    actor.adv3d.asset_id = ""
    ego = bpy.data.objects["ego"]
    original = load_scene(scene_file)
    frames = np.arange(original.frames)
    yaw = ops_scene.eval_curve(ego, "rotation_euler", 2, frames)
    yaw[30:32] += 0.2
    ops_scene.set_keys(ego, "rotation_euler", 2, frames, yaw)
    assert bpy.ops.adv3d.scene_export(filepath=str(tmp_path / "turned.json")) == {"FINISHED"}
    edited = load_scene(tmp_path / "turned.json")
    np.testing.assert_allclose(edited.ego.track.yaw[30:32], original.ego.track.yaw[30:32] + 0.2, atol=1.5e-3)
    np.testing.assert_array_equal(edited.ego.track.speed, original.ego.track.speed)
    np.testing.assert_array_equal(edited.ego.track.x, original.ego.track.x)


def test_scene_apply_asset_swaps_mesh(ctx, data, lib_copy):
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    actor = bpy.data.objects["actor 3"]
    ctx.view_layer.objects.active = actor
    actor.adv3d.asset_id = "fx.suv"
    assert bpy.ops.adv3d.scene_apply_asset() == {"FINISHED"}
    assert actor.data.name == "asset:fx.suv" and len(actor.data.vertices) > 8
    actor.adv3d.asset_id = "no.such"
    with pytest.raises(RuntimeError, match="no.such"):
        bpy.ops.adv3d.scene_apply_asset()


def test_malformed_scene_is_reported(ctx, data, tmp_path):
    doc = json.loads(Path(data["scene"]).read_text())
    doc["actors"][1]["track"]["yaw"] = doc["actors"][1]["track"]["yaw"][:-1]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(RuntimeError, match=r"\$\.actors\[1\]\.track\.yaw"):
        bpy.ops.adv3d.scene_load(filepath=str(bad))
    assert "Adv3D Scene" not in bpy.data.collections
    with pytest.raises(RuntimeError, match="no scene loaded"):
        bpy.ops.adv3d.scene_export(filepath=str(tmp_path / "out.json"))


# --------------------------------------------------------------------------- packaging

def test_manifest_checks_catch_problems():
    from adv3d_runner.blender_cli import check_manifest

    good = {"schema_version": "1.0.0", "id": "adv3d", "version": "0.1.0", "name": "Adv3D", "tagline": "t",
            "maintainer": "m", "type": "add-on", "blender_version_min": "4.2.0", "blender_version_max": "5.1.0",
            "license": ["SPDX:GPL-3.0-or-later"], "copyright": ["2026 adv3d developers"],
            "wheels": ["./wheels/adv3d-0.1.0-py3-none-any.whl"]}
    names = {"__init__.py", "blender_manifest.toml", "LICENSE", "wheels/adv3d-0.1.0-py3-none-any.whl"}
    assert check_manifest(good, names, "z") == []
    assert any("license: expected one of" in p for p in check_manifest(dict(good, license=["SPDX:MIT"]), names, "z"))
    assert any("copyright" in p for p in check_manifest({k: v for k, v in good.items() if k != "copyright"}, names, "z"))
    assert any("LICENSE" in p for p in check_manifest(good, names - {"LICENSE"}, "z"))
    assert any("not in the archive" in p for p in check_manifest(good, names - {"wheels/adv3d-0.1.0-py3-none-any.whl"}, "z"))
    bad = dict(good, wheels=good["wheels"] + ["./wheels/numpy-1.26.4-cp311-cp311-linux_x86_64.whl"])
    assert any("must not be shipped" in p for p in check_manifest(bad, names | {bad["wheels"][1][2:]}, "z"))
    assert any("schema_version" in p for p in check_manifest(dict(good, schema_version="0.9"), names, "z"))
    assert any("blender_version_max" in p for p in check_manifest({**good, "blender_version_max": ""}, names, "z"))
    assert any("development file" in p for p in check_manifest(good, names | {"selfcheck.py"}, "z"))
    # (the real zip: tests/test_blender_stock.py)


# --------------------------------------------------------------------------- review engine

def _review_data(frames: int = 12, seed: int = 0):
    from blender_addon import review

    rng = np.random.default_rng(seed)
    ego = np.stack([np.arange(frames) * 1.0, np.zeros(frames), np.zeros(frames)], axis=1)
    gone = np.stack([20 + np.arange(frames) * 0.8, np.full(frames, 3.5), np.full(frames, 0.1)], axis=1)
    gone[8:] = np.nan  # leaves the scene at frame 8
    actors = [review.ReviewActor(1, gone, np.array([4.5, 1.8, 1.5]), adversarial=True),
              review.ReviewActor(2, gone + [5, 0, 0], np.array([4.0, 1.7, 1.4]))]
    points = [rng.random((50 + 10 * t, 3)).astype(np.float32) * 30 for t in range(frames)]
    dets = [np.column_stack([rng.random((t % 3 + 1, 2)) * 30, np.zeros(t % 3 + 1),
                             np.tile([4.5, 1.8, 1.5], (t % 3 + 1, 1)), rng.random(t % 3 + 1)]) for t in range(frames)]
    preds = [rng.random((2, 6, 2)) * 30 for _ in range(frames)]
    plan = [np.column_stack([np.linspace(t, t + 30, 10), np.linspace(0, 1, 10)]) for t in range(frames)]
    return review.ReviewData(ego, np.array([4.8, 1.9, 1.55]), actors, points, dets, preds, plan)


def test_review_objects_follow_the_timeline(ctx):
    from blender_addon import meshdata, review

    data = _review_data()
    counts = review.build_review(ctx.scene, data)
    assert counts == {"frames": 12, "actors": 2, "adversarial": 1}
    assert review.on_frame_change in bpy.app.handlers.frame_change_post
    objs = bpy.data.objects
    assert objs["review actor 1"]["adv3d_adversarial"] and not objs["review actor 2"]["adv3d_adversarial"]
    for frame in (0, 5, 11):
        ctx.scene.frame_set(frame)
        lidar = objs["review lidar"].data
        co = np.empty(len(lidar.vertices) * 3, np.float32)
        lidar.vertices.foreach_get("co", co)
        np.testing.assert_array_equal(co.reshape(-1, 3), data.points[frame])
        v, f = meshdata.mesh_arrays(objs["review detections"].data)
        assert len(v) == 8 * len(data.detections[frame]) and len(f) == 12 * len(data.detections[frame])
        centre = v[:8].mean(axis=0)
        assert centre[:2] == pytest.approx(data.detections[frame][0, :2], abs=1e-4)
        plan = objs["review plan"].data.splines[0].points
        got = np.array([p.co[:2] for p in plan])
        np.testing.assert_allclose(got, data.plan[frame], atol=1e-4)
        assert len(objs["review predictions"].data.splines) == 2
        actor = objs["review actor 1"]
        assert actor.hide_render == (frame >= 8)
        if frame < 8:
            assert actor.location.x == pytest.approx(data.actors[0].poses[frame, 0], abs=1e-4)
    review.clear_review(ctx.scene)
    assert "review lidar" not in bpy.data.objects
    assert not ctx.scene.adv3d.review.key and review.data_of(ctx.scene) is None


def test_review_rejects_inconsistent_data(ctx):
    from adv3d_runner.errors import Adv3dError
    from blender_addon import review

    data = _review_data()
    data.points = data.points[:-1]
    with pytest.raises(Adv3dError, match="points"):
        review.build_review(ctx.scene, data)


def test_bundled_scenes_round_trip_identically(ctx, repo_root, tmp_path):
    """Real data: a generated highway scene and a CommonRoad import (read-only from the repo)."""
    import gzip

    picks = sorted((repo_root / "scenes" / "real").glob("*.json.gz"))[:1] + \
        sorted((repo_root / "scenes" / "highway").glob("*.json.gz"))[:1]
    if not picks:
        pytest.skip("no bundled scenes in this checkout")
    for path in picks:
        assert bpy.ops.adv3d.scene_load(filepath=str(path)) == {"FINISHED"}
        out = tmp_path / path.name
        assert bpy.ops.adv3d.scene_export(filepath=str(out)) == {"FINISHED"}
        assert gzip.decompress(out.read_bytes()) == gzip.decompress(path.read_bytes()), path.name


class _Layout:
    """Stand-in for UILayout: checks that every drawn property and operator exists."""

    def __init__(self, seen):
        self.seen = seen

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.seen.append(name)

    def operator(self, idname, **kw):
        mod, op = idname.split(".")
        assert hasattr(getattr(bpy.ops, mod), op), idname
        assert getattr(getattr(bpy.ops, mod), op).poll is not None
        self.seen.append(idname)
        return _Props()

    def template_list(self, listtype, list_id, data, prop, active_data, active_prop, **kw):
        assert prop in data.bl_rna.properties and active_prop in active_data.bl_rna.properties
        assert hasattr(bpy.types, listtype)

    def label(self, **kw):
        pass

    def __getattr__(self, name):  # row(), column(), box(), scale_y, ...
        return lambda *a, **kw: _Layout(self.seen)


class _Props:
    def __setattr__(self, name, value):
        pass


def test_panels_draw_with_existing_properties_and_operators(ctx, data, lib_copy):
    from types import SimpleNamespace

    from blender_addon import panels

    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    bpy.ops.adv3d.scene_load(filepath=str(data["scene"]))
    ctx.view_layer.objects.active = bpy.data.objects["actor 3"]
    seen = []
    for panel in (panels.ADV3D_PT_library, panels.ADV3D_PT_shapes, panels.ADV3D_PT_scenes):
        panel.draw(SimpleNamespace(layout=_Layout(seen)), ctx)
    for expected in ("adv3d.library_import", "adv3d.shapes_random", "adv3d.scene_export", "latent", "asset_id"):
        assert expected in seen


def test_render_resolves_relative_paths_against_the_callers_folder(data, tmp_path, repo_root):
    """``adv3d blender render`` run from another folder: ``--out`` and ``--space`` mean the
    caller's paths; ``--panel`` adds the panel column (drawn from the panel's properties)."""
    import os
    import subprocess
    import sys

    from PIL import Image

    shutil.copy(data["space"], tmp_path / "space.npz")
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    cmd = [sys.executable, "-m", "adv3d_runner.cli", "--quiet", "blender", "render", "--what", "shapes", "--panel",
           "--space", "space.npz", "--u", "0.2,0.8,0.5,0.5,0.5", "--size", "200x120", "--out", "pics/shape.png"]
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    img = Image.open(tmp_path / "pics" / "shape.png")
    assert img.size == (200 + 330, 120)
    assert not (repo_root / "pics").exists()
    bad = subprocess.run(cmd[:-1] + ["out.png", "--u", "0.5"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert bad.returncode != 0 and "--u needs 5 values" in bad.stderr


def _imported_extents(before: set) -> np.ndarray:
    """Extents (x, y, z) in metres of the mesh objects an importer just added."""
    new = [o for o in bpy.data.objects if o.name not in before and o.type == "MESH"]
    assert new
    pts = np.concatenate([np.array([o.matrix_world @ v.co for v in o.data.vertices]) for o in new])
    return pts.max(axis=0) - pts.min(axis=0)


def test_exports_open_upright_in_blenders_importers_with_their_defaults(ctx, data, tmp_path):
    """Auto up axis: Blender's OBJ, PLY, STL and glTF importers with their default settings stand
    the car up (length along x, height along z); two .gltf files in one folder keep their own
    buffers (both import)."""
    from adv3d_runner.shapes.shape_space import ShapeSpace

    bpy.ops.adv3d.shapes_load(filepath=str(data["space"]))
    v, _ = ShapeSpace.load(data["space"]).decode_arrays(
        __import__("blender_addon").ops_shapes.current_unit(ctx.scene.adv3d.shapes))
    want = v.max(axis=0) - v.min(axis=0)
    importers = {"obj": bpy.ops.wm.obj_import, "ply": bpy.ops.wm.ply_import, "stl": bpy.ops.wm.stl_import,
                 "gltf": bpy.ops.import_scene.gltf}
    for ext, fmt in (("obj", "OBJ"), ("ply", "PLY"), ("stl", "STL"), ("gltf", "GLTF")):
        path = tmp_path / f"car.{ext}"
        assert bpy.ops.adv3d.shapes_export(filepath=str(path), file_format=fmt) == {"FINISHED"}
        before = set(bpy.data.objects.keys())
        importers[ext](filepath=str(path))
        assert np.allclose(_imported_extents(before), want, atol=2e-3), ext
    # Z up OBJ lies on its side in the OBJ importer's defaults; Z up glTF is refused
    assert bpy.ops.adv3d.shapes_export(filepath=str(tmp_path / "z.obj"), up_axis="Z") == {"FINISHED"}
    before = set(bpy.data.objects.keys())
    bpy.ops.wm.obj_import(filepath=str(tmp_path / "z.obj"))
    assert not np.allclose(_imported_extents(before), want, atol=2e-3)
    with pytest.raises(RuntimeError, match="glTF is always y up"):
        bpy.ops.adv3d.shapes_export(filepath=str(tmp_path / "z.glb"), up_axis="Z")
    # a second .gltf in the same folder: its own buffer, the first one still imports
    bpy.context.scene.adv3d.shapes.latent[0] = 0.1
    assert bpy.ops.adv3d.shapes_export(filepath=str(tmp_path / "second.gltf")) == {"FINISHED"}
    assert sorted(p.name for p in tmp_path.glob("*.bin")) == ["car.bin", "second.bin"]
    for name in ("car.gltf", "second.gltf"):
        before = set(bpy.data.objects.keys())
        assert bpy.ops.import_scene.gltf(filepath=str(tmp_path / name)) == {"FINISHED"}
        assert _imported_extents(before)[2] > 0.5


def test_first_slider_move_never_waits_for_the_realism_reference(ctx, tmp_path):
    """Your own library and a space built from it (no shipped reference): the first slider move
    is fast, the reference is built in the background from the Library panel's library and kept
    by content in the cache folder, so the next session has it at its first move."""
    import time

    from adv3d_runner.shapes import realism
    from blender_addon import runner

    lib = make_library(tmp_path / "own")
    space_file = make_space(tmp_path / "own.npz")
    runner.clear_space_cache()
    runner.clear_reference_state()
    space = runner.load_space(space_file)
    cache_file = realism.cached_reference_path(space)
    cache_file.unlink(missing_ok=True)                      # (an earlier test's build of this space)
    ctx.scene.adv3d.library.path = str(lib)
    assert bpy.ops.adv3d.shapes_load(filepath=str(space_file)) == {"FINISHED"}
    shapes = ctx.scene.adv3d.shapes
    # CPU time of this thread: what the move costs on an idle machine (the shared test machine's
    # load stretches wall time; the child Python that builds the reference is not counted)
    t0 = time.thread_time()
    shapes.latent[0] = 0.2                                 # background mode: the update runs at once
    assert time.thread_time() - t0 < 0.1
    assert "in the background" in shapes.realism_live
    runner.realism_reference(space, wait=True)              # the build finishes
    assert cache_file.is_file()
    shapes.latent[0] = 0.3
    assert shapes.realism_live.startswith("JSD ") and "lacks" not in shapes.realism_live
    runner.clear_space_cache()                              # a new session: the cache file has it
    runner.clear_reference_state()
    assert bpy.ops.adv3d.shapes_load(filepath=str(space_file)) == {"FINISHED"}
    t0 = time.thread_time()
    shapes.latent[0] = 0.4
    assert time.thread_time() - t0 < 0.1 and shapes.realism_live.startswith("JSD ")
    # a space whose assets no library holds: one clear line, no traceback
    runner.clear_reference_state()
    cache_file.unlink()
    ctx.scene.adv3d.library.path = ""
    shapes.latent[0] = 0.5
    with pytest.raises(runner.Adv3dError, match="no library holds its assets"):
        runner.realism_reference(space, wait=True)
    shapes.latent[0] = 0.6
    assert "no library holds its assets" in shapes.realism_live


# --------------------------------------------------------------------------- import: what the CLI keeps

RED = (200, 30, 30, 255)


def _red_car(path: Path) -> Path:
    """A car in adv3d's frame whose body is red and cabin grey, written by trimesh (glb/obj)."""
    mesh = _vehicle_mesh(4.4, 1.8, 1.4, 0.5)
    colours = np.tile(np.array([150, 150, 150, 255], np.uint8), (len(mesh.faces), 1))
    colours[:12] = RED  # the body box
    mesh.visual.face_colors = colours
    from adv3d_runner.shapes.mesh_io import write_mesh

    write_mesh(mesh, path)
    return path


def _stored_colours(lib_file: Path, asset_id: str) -> set:
    from adv3d_runner.shapes.library import load_library
    from adv3d_runner.shapes.mesh_io import read_library_mesh

    library = load_library(lib_file)
    mesh = read_library_mesh(library.path_of(library.get(asset_id)))
    return {tuple(int(c) for c in row) for row in np.asarray(mesh.visual.face_colors)}


def test_import_keeps_colours_as_the_cli_does_and_takes_every_cli_format(ctx, lib_copy, tmp_path):
    """A coloured glb stores the same face colours as `adv3d assets import`; an FBX (through
    Blender's importer) keeps its material colour; ApolloCar3D .json (the CLI's reader and
    convention) comes in upright; the file types offered are the CLI importer's."""
    from adv3d_runner.shapes.library import add_asset, load_library, load_or_new_library
    from adv3d_runner.shapes.mesh_io import SUPPORTED_FORMATS, import_vehicle
    from blender_addon import ops_library
    from test_mesh_io import _apollo_json

    assert set(SUPPORTED_FORMATS) <= set(ops_library.IMPORT_SUFFIXES)
    assert set(SUPPORTED_FORMATS) <= set(ops_library.ADV3D_FH_vehicle.bl_file_extensions.split(";"))
    src = tmp_path / "pack"
    src.mkdir()
    (src / "License.txt").write_text(CC0)
    _red_car(src / "red.glb")
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    assert bpy.ops.adv3d.library_import(filepath=str(src / "red.glb")) == {"FINISHED"}
    cli_lib = tmp_path / "cli" / "library.json"
    add_asset(load_or_new_library(cli_lib), cli_lib, src / "red.glb", "sedan", lambda p: import_vehicle(p))
    assert RED in _stored_colours(lib_copy, "pack.red")
    assert _stored_colours(lib_copy, "pack.red") == _stored_colours(cli_lib, "pack.red")
    # FBX: Blender's importer, material colour kept
    car = _vehicle_mesh(4.4, 1.8, 1.4, 0.5)
    me = bpy.data.meshes.new("red car")
    me.from_pydata(car.vertices.tolist(), [], car.faces.tolist())
    mat = bpy.data.materials.new("red paint")
    if mat.node_tree is None:  # Blender 4.x; node-based by default from 5.0
        mat.use_nodes = True
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.58, 0.012, 0.012, 1.0)
    me.materials.append(mat)
    ctx.scene.collection.objects.link(bpy.data.objects.new("red car", me))
    bpy.ops.export_scene.fbx(filepath=str(src / "red.fbx"), use_selection=False)
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    assert bpy.ops.adv3d.library_import(filepath=str(src / "red.fbx"), asset_id="pack.red-fbx") == {"FINISHED"}
    assert any(abs(c[0] - RED[0]) <= 2 and c[1] < 60 for c in _stored_colours(lib_copy, "pack.red-fbx"))
    # ApolloCar3D .json: camera frame, upright after import
    _apollo_json(src / "apollo.json", _vehicle_mesh(4.6, 1.8, 1.5, 0.5))
    assert bpy.ops.adv3d.library_import(filepath=str(src / "apollo.json")) == {"FINISHED"}
    assert load_library(lib_copy).get("pack.apollo").dimensions == pytest.approx((4.6, 1.8, 1.5), abs=2e-3)


def test_import_several_files_named_licence_replace_and_new_library(ctx, tmp_path):
    """New library makes an empty one; several files import at once; a pack without a licence
    file imports when the licence is named (a note is stored as its licence file); an id already
    in the library is refused unless Replace is on."""
    from adv3d_runner.shapes.library import load_library

    bpy.ops.adv3d.library_new(directory=str(tmp_path / "mylib"))
    lib_file = tmp_path / "mylib" / "library.json"
    assert lib_file.is_file() and ctx.scene.adv3d.library.path == str(lib_file)
    with pytest.raises(RuntimeError, match="exists already"):
        bpy.ops.adv3d.library_new(directory=str(tmp_path / "mylib"))
    src = tmp_path / "nolicence"
    src.mkdir()
    _red_car(src / "a.glb")
    _red_car(src / "b.obj")
    files = [{"name": "a.glb"}, {"name": "b.obj"}]
    with pytest.raises(RuntimeError, match="no licence file beside it; give the licence file or name"):
        bpy.ops.adv3d.library_import(directory=str(src), files=files)
    assert bpy.ops.adv3d.library_import(directory=str(src), files=files, licence_name="CC-BY-4.0",
                                        axis_up="Z") == {"FINISHED"}
    library = load_library(lib_file)
    assert library.ids() == ["nolicence.a", "nolicence.b"]
    # what a drop onto the viewport calls: the file handler's operator invoked with the files
    handler = bpy.types.FileHandler.bl_rna_get_subclass_py("ADV3D_FH_vehicle")
    assert handler is not None and handler.bl_import_operator == "adv3d.library_import"
    _red_car(src / "dropped.glb")
    assert bpy.ops.adv3d.library_import("INVOKE_DEFAULT", directory=str(src), files=[{"name": "dropped.glb"}],
                                        licence_name="CC-BY-4.0") == {"FINISHED"}
    assert "nolicence.dropped" in load_library(lib_file).ids()
    a = library.get("nolicence.a")
    assert a.licence["name"] == "CC-BY-4.0" and "CC-BY-4.0" in (lib_file.parent / a.licence["file"]).read_text()
    assert len(ctx.scene.adv3d.library.assets) == 3  # a, b and the dropped one
    with pytest.raises(RuntimeError, match="already in the library"):
        bpy.ops.adv3d.library_import(filepath=str(src / "a.glb"), licence_name="CC-BY-4.0", length=3.0)
    assert load_library(lib_file).get("nolicence.a").dimensions[0] == pytest.approx(4.4, abs=2e-3)
    assert bpy.ops.adv3d.library_import(filepath=str(src / "a.glb"), licence_name="CC-BY-4.0", length=3.0,
                                        replace=True) == {"FINISHED"}
    assert load_library(lib_file).get("nolicence.a").dimensions[0] == pytest.approx(3.0, abs=2e-3)


def test_build_steps_stay_short_from_a_fresh_session(lib_copy, repo_root):
    """In a session that has not imported trimesh, scipy or networkx yet (a fresh Blender), no
    step of the modal Build comes near half a second of CPU: the heavy imports are split up."""
    code = (
        "import json, sys, time\n"
        "import bpy\n"
        "import blender_addon\n"
        "from blender_addon import jobs, ops_shapes\n"
        "from adv3d_runner.shapes.library import load_library\n"
        "blender_addon.register()\n"
        "fresh = not any(m in sys.modules for m in ('trimesh', 'networkx', 'scipy.spatial'))\n"
        "job = jobs.Job('Build', ops_shapes.build_steps(load_library(sys.argv[1]), sys.argv[2],"
        " {'k': 2, 'resolution': 16}))\n"
        "loads = []\n"
        "while job.run_slice(0.0) == jobs.RUNNING:\n"
        "    if job.message.startswith('loading '):\n"
        "        loads.append(job.message)\n"
        "print(json.dumps({'fresh': fresh, 'state': job.state, 'cpu': job.max_step_cpu_s, 'slowest': job.slowest,"
        " 'loads': loads}))\n")
    out = subprocess.run([sys.executable, "-c", code, str(lib_copy), str(lib_copy.parent / "fresh.npz")],
                         capture_output=True, text=True, cwd=repo_root, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["fresh"] and res["state"] == "done"
    from blender_addon import jobs

    assert res["cpu"] < jobs.MAX_STEP_S, res
    # trimesh's import is cut into its heavy parts, one step each (whole, it took 0.34 s of CPU
    # here and 0.98 s on a reviewer's machine: too close to, or over, the limit)
    parts = [m for m in res["loads"] if m.split()[-1].startswith(("scipy", "networkx", "trimesh"))]
    assert len(parts) >= 4 and "loading trimesh.util" in res["loads"], res["loads"]


def test_build_refuses_more_components_than_the_assets_give(ctx, lib_copy, tmp_path):
    bpy.ops.adv3d.library_load(filepath=str(lib_copy))
    shapes = ctx.scene.adv3d.shapes
    shapes.space_path = str(tmp_path / "k.npz")
    shapes.build_k = len(FIXTURE_CARS)  # 4 assets span 3 directions
    with pytest.raises(RuntimeError, match=r"K=4 is more than 4 included assets can give \(at most 3"):
        bpy.ops.adv3d.shapes_build()
    assert not (tmp_path / "k.npz").exists()
