"""The vehicle library contract, the shipped library, and ``adv3d assets``."""
from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import trimesh

from adv3d_runner.cli import main
from adv3d_runner.errors import FileFormatError
from adv3d_runner.shapes.library import (DEFAULT_LIBRARY, VehicleAsset, VehicleLibrary, load_asset_mesh,
                                         load_library, save_library)
from adv3d_runner.shapes.library_cli import check_library
from adv3d_runner.vehicle_classes import TYPICAL_DIMENSIONS

# Every road vehicle body of the ten source packs (variants, race cars and wheel-less shells are
# recorded as excluded, with the reason).
EXPECTED_SOURCES = {
    ("quaternius-cars", f) for f in ("Cop.blend", "NormalCar1.blend", "NormalCar2.blend", "SUV.blend",
                                     "SportsCar.blend", "SportsCar2.blend", "Taxi.blend")
} | {
    ("quaternius-transport", f) for f in ("Ambulance.blend", "Bus.blend", "SchoolBus.blend", "Taxi.blend")
} | {
    ("kenney-car-kit", f + ".glb") for f in ("ambulance", "delivery", "delivery-flat", "firetruck", "garbage-truck",
                                             "hatchback-sports", "police", "sedan", "sedan-sports", "suv",
                                             "suv-luxury", "taxi", "truck", "truck-flat", "van")
} | {
    ("quaternius-cars-bundle", "car-pickup.glb"),
    ("quaternius-car-pack-2016", "Car.blend"), ("quaternius-car-pack-2016", "SimpleCar.blend"),
    ("quaternius-car-pack-2016", "Truck.blend"),
    ("quaternius-basic-car-pack-2017", "BasicCar.blend"), ("quaternius-basic-car-pack-2017", "SimpleCarHigh.blend"),
    ("kaykit-city-builder-bits", "car_hatchback.gltf"), ("kaykit-city-builder-bits", "car_sedan.gltf"),
    ("kaykit-city-builder-bits", "car_stationwagon.gltf"),
    ("khronos-cesium-milk-truck", "CesiumMilkTruck.glb"),
    ("openmaterial-examples", "vehicle_example.gltf"), ("openmaterial-examples", "truck_example.gltf"),
}
EXPECTED_EXCLUDED = {
    ("kenney-car-kit", "race.glb"), ("kenney-car-kit", "race-future.glb"),
    ("quaternius-basic-car-pack-2017", "SimpleCarShort.blend"), ("quaternius-basic-car-pack-2017", "Taxi.blend"),
    ("quaternius-basic-car-pack-2017", "CopCar.blend"), ("quaternius-basic-car-pack-2017", "RaceCar.blend"),
    ("kaykit-city-builder-bits", "car_taxi.gltf"), ("kaykit-city-builder-bits", "car_police.gltf"),
    ("godot-truck-town", "meshes.glb"),
}
#: Licences of the packs; attribution and share-alike travel with the files (their texts are
#: copied beside the meshes).
PACK_LICENCES = {"khronos-cesium-milk-truck": "LicenseRef-CC-BY-TM", "openmaterial-examples": "CC-BY-SA-4.0"}
PAPER_CLASSES = {"sedan", "hatchback", "sports", "suv", "van", "pickup"}


@pytest.fixture(scope="module")
def shipped() -> VehicleLibrary:
    return load_library(DEFAULT_LIBRARY)


# ----------------------------------------------------------------------------- shipped library

def test_shipped_library_has_every_road_vehicle(shipped):
    sources = {(a.source["pack"], a.source["file"]) for a in shipped.assets}
    assert sources == EXPECTED_SOURCES
    excluded = {(e["pack"], e["file"]) for e in shipped.excluded}
    assert excluded == EXPECTED_EXCLUDED
    assert all(len(e["reason"]) > 20 for e in shipped.excluded)


def test_shipped_meshes_load_and_match_their_records(shipped):
    # dimensions within 1 mm, triangle counts, lowest point z = 0, footprint centred, licences
    assert check_library(shipped, tolerance=1e-3) == []


def test_shipped_library_round_trips_byte_exact(shipped, tmp_path):
    out = tmp_path / "library.json"
    save_library(shipped, out)
    assert out.read_bytes() == DEFAULT_LIBRARY.read_bytes()
    again = load_library(out)
    assert again.assets == shipped.assets and again.excluded == shipped.excluded


def test_shape_space_selection(shipped):
    space = shipped.shape_space_assets()
    assert len(space) >= 10
    assert {a.vehicle_class for a in space} <= PAPER_CLASSES
    assert {a.vehicle_class for a in space} >= {"sedan", "sports", "suv", "van", "pickup"}
    for a in shipped.assets:
        if a.vehicle_class in ("bus", "fire_truck", "garbage_truck", "truck", "ambulance"):
            assert not a.in_shape_space, a.id
    assert [a.id for a in shipped.by_class("bus")] == ["quaternius-transport.bus", "quaternius-transport.schoolbus"]


def test_shipped_dimensions_are_plausible_for_their_class(shipped):
    for a in shipped.assets:
        typical = TYPICAL_DIMENSIONS[a.vehicle_class]
        ratios = np.asarray(a.dimensions) / np.asarray(typical)
        assert np.all((ratios > 0.7) & (ratios < 1.3)), (a.id, a.dimensions, typical)


def test_curated_kenney_assets_record_what_was_done(shipped):
    for a in shipped.assets:
        if a.source["pack"] == "kenney-car-kit":
            assert "scale_factors" in a.curation and "size_before_scaling" in a.curation
            assert a.curation["scaled_to_dimensions"] == pytest.approx(list(a.dimensions), abs=1e-3)
            assert a.curation.get("note")
        assert a.licence["name"] == PACK_LICENCES.get(a.source["pack"], "CC0-1.0")
        assert (shipped.root / a.licence["file"]).is_file()
        if a.source["pack"] not in ("kenney-car-kit", "quaternius-cars", "quaternius-transport"):
            assert (shipped.root / a.source["pack"] / "SOURCE.txt").is_file()  # provenance travels too


def test_load_asset_mesh_front_is_plus_x(shipped):
    # Quaternius cars have a long bonnet: the roof's highest point lies behind the middle
    for aid in ("quaternius-cars.normalcar1", "quaternius-cars.sportscar"):
        m = load_asset_mesh(shipped, aid)
        v = np.asarray(m.vertices)
        assert v[np.argmax(v[:, 2]), 0] < 0.0, aid
    with pytest.raises(KeyError, match="no-such-car"):
        load_asset_mesh(shipped, "no-such-car")


# ----------------------------------------------------------------------------- contract errors

def _doc() -> dict:
    return json.loads(DEFAULT_LIBRARY.read_text())


def _mutations():
    def set_(path, value):
        def f(doc):
            obj = doc
            for key in path[:-1]:
                obj = obj[key]
            obj[path[-1]] = value
        return f

    def delete(path):
        def f(doc):
            obj = doc
            for key in path[:-1]:
                obj = obj[key]
            del obj[path[-1]]
        return f

    return [
        (set_(["format"], "something-else"), "$.format"),
        (set_(["version"], 2), "$.version"),
        (set_(["assets"], {}), "$.assets"),
        (set_(["assets", 0, "dimensions"], [4.5, -1.8, 1.4]), "$.assets[0].dimensions[1]"),
        (set_(["assets", 1, "dimensions"], [4.5, 1.8]), "$.assets[1].dimensions"),
        (set_(["assets", 2, "dimensions"], [4.5, "wide", 1.4]), "$.assets[2].dimensions[1]"),
        (delete(["assets", 3, "id"]), "$.assets[3].id"),
        (set_(["assets", 3, "id"], "Has Spaces"), "$.assets[3].id"),
        (set_(["assets", 4, "id"], None), "$.assets[4].id"),
        (set_(["assets", 5, "in_shape_space"], "yes"), "$.assets[5].in_shape_space"),
        (set_(["assets", 5, "triangle_count"], True), "$.assets[5].triangle_count"),
        (set_(["assets", 6, "file"], "../../etc/passwd"), "$.assets[6].file"),
        (set_(["assets", 6, "file"], "/abs/car.glb"), "$.assets[6].file"),
        (set_(["assets", 7, "licence", "file"], None), "$.assets[7].licence.file"),
        (delete(["assets", 7, "source", "pack"]), "$.assets[7].source.pack"),
        (set_(["assets", 8, "cleaning"], []), "$.assets[8].cleaning"),
        (set_(["assets", 8, "colour"], "red"), "$.assets[8].colour"),
        (set_(["assets", 9, "class"], "Sedan!"), "$.assets[9].class"),
        (set_(["excluded", 0, "reason"], ""), "$.excluded[0].reason"),
        (lambda doc: doc["assets"].append(copy.deepcopy(doc["assets"][0])), f"$.assets[{len(_doc()['assets'])}].id"),
    ]


@pytest.mark.parametrize("mutate,field", _mutations())
def test_malformed_fields_name_file_and_json_path(tmp_path, mutate, field):
    doc = _doc()
    mutate(doc)
    path = tmp_path / "library.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError) as info:
        load_library(path)
    assert info.value.field == field
    assert str(path) in str(info.value)


def test_not_json_and_missing_file(tmp_path):
    bad = tmp_path / "library.json"
    bad.write_text("{ not json")
    with pytest.raises(FileFormatError, match="library.json"):
        load_library(bad)
    with pytest.raises(FileFormatError, match="nothing.json"):
        load_library(tmp_path / "nothing.json")


def test_save_refuses_an_invalid_library_and_keeps_the_old_file(tmp_path):
    path = tmp_path / "library.json"
    good = VehicleLibrary(root=tmp_path, assets=[VehicleAsset(
        id="a", file="p/a.glb", vehicle_class="sedan", dimensions=(4.5, 1.8, 1.4),
        source={"pack": "p", "file": "a.obj"}, licence={"name": "CC0-1.0", "file": "p/LICENSE"},
        triangle_count=12)])
    save_library(good, path)
    before = path.read_bytes()
    bad = VehicleLibrary(root=tmp_path, assets=[*good.assets, good.assets[0]])  # duplicate id
    with pytest.raises(FileFormatError, match=r"\$\.assets\[1\]\.id"):
        save_library(bad, path)
    assert path.read_bytes() == before
    assert load_library(path).assets == good.assets


# ----------------------------------------------------------------------------- the CLI

def _write_car_cm(path):
    body = trimesh.creation.box(extents=(300.0, 150.0, 120.0))  # toy car in centimetres
    body.apply_translation((1e5, 5e4, 60.0 + 1e4))
    nose = trimesh.creation.box(extents=(20.0, 40.0, 20.0))
    nose.apply_translation((1e5 + 160.0, 5e4, 50.0 + 1e4))
    trimesh.util.concatenate([body, nose]).export(path)


def test_cli_import_check_list_and_replace(tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    _write_car_cm(src / "ToyCar.obj")
    (src / "LICENSE.txt").write_text("CC0 1.0 Universal, public domain dedication\n")
    lib = tmp_path / "lib" / "library.json"
    argv = ["-q", "assets", "import", str(src / "ToyCar.obj"), "--class", "sedan", "--library", str(lib),
            "--source-pack", "toys", "--up=+z", "--forward=+x"]
    assert main(argv) == 0
    library = load_library(lib)
    (asset,) = library.assets
    assert asset.id == "toys.toycar" and asset.file == "toys/toycar.glb"
    assert asset.dimensions == pytest.approx((3.2, 1.5, 1.2), abs=1e-4)
    assert asset.licence == {"name": "CC0-1.0", "file": "toys/LICENSE.txt"}
    assert (lib.parent / "toys" / "LICENSE.txt").is_file()
    assert asset.curation["unit"].startswith("cm")
    assert asset.in_shape_space
    assert main(["-q", "assets", "check", "--library", str(lib)]) == 0

    # re-import with real dimensions: the entry is replaced, scaling recorded
    assert main(argv + ["--dimensions", "4.7", "1.8", "1.45", "--note", "toy to sedan",
                        "--exclude-from-shape-space"]) == 0
    library = load_library(lib)
    (asset,) = library.assets
    assert asset.dimensions == pytest.approx((4.7, 1.8, 1.45), abs=1e-4)
    assert asset.curation["size_before_scaling"] == pytest.approx([3.2, 1.5, 1.2], abs=1e-4)
    assert asset.curation["scale_factors"][0] == pytest.approx(4.7 / 3.2, abs=1e-4)
    assert asset.curation["note"] == "toy to sedan"
    assert not asset.in_shape_space
    mesh = load_asset_mesh(library, asset.id)
    assert mesh.extents == pytest.approx([4.7, 1.8, 1.45], abs=1e-4)
    assert len(mesh.faces) == asset.triangle_count == 24
    capsys.readouterr()
    assert main(["assets", "list", "--library", str(lib)]) == 0
    assert "toys.toycar" in capsys.readouterr().out

    # a broken mesh file is found by check
    (lib.parent / "toys" / "toycar.glb").write_bytes(b"garbage")
    assert main(["-q", "assets", "check", "--library", str(lib)]) == 1
    assert "toycar.glb" in capsys.readouterr().out


def test_cli_import_of_a_non_mesh_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "fake.glb"
    bad.write_text("not a mesh")
    (tmp_path / "LICENSE.txt").write_text("CC0\n")
    lib = tmp_path / "library.json"
    assert main(["assets", "import", str(bad), "--class", "sedan", "--library", str(lib)]) == 1
    err = capsys.readouterr().err
    assert "fake.glb" in err and "Traceback" not in err
    assert not lib.exists()  # nothing written for a failed import


def test_cli_import_needs_a_licence(tmp_path, capsys):
    _write_car_cm(tmp_path / "car.obj")
    assert main(["assets", "import", str(tmp_path / "car.obj"), "--class", "sedan",
                 "--library", str(tmp_path / "library.json")]) == 1
    assert "licence" in capsys.readouterr().err


@pytest.mark.slow
def test_build_script_reproduces_the_shipped_library_byte_for_byte(repo_root, tmp_path):
    import subprocess

    packs = repo_root.parent / "shared" / "vehicle-packs"
    if not packs.is_dir():
        pytest.skip(f"source packs not found at {packs}")
    env = {**__import__("os").environ, "ADV3D_LIBRARY_DIR": str(tmp_path), "OMP_NUM_THREADS": "1"}
    subprocess.run(["bash", str(repo_root / "assets/vehicles/build_library.sh"), str(packs)],
                   check=True, env=env, capture_output=True, timeout=1200)
    shipped_files = sorted(p.relative_to(DEFAULT_LIBRARY.parent) for p in DEFAULT_LIBRARY.parent.rglob("*")
                           if p.is_file() and p.suffix in (".json", ".glb", ".txt", ".md"))
    built_files = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")
                         if p.is_file() and p.suffix in (".json", ".glb", ".txt", ".md"))
    assert built_files == shipped_files
    for rel in shipped_files:
        assert (tmp_path / rel).read_bytes() == (DEFAULT_LIBRARY.parent / rel).read_bytes(), rel


# ----------------------------------------------------------------------------- add_asset (CLI and add-on)

def test_add_asset_checks_before_reading_and_stores_like_the_cli(tmp_path):
    from adv3d_runner.errors import ConfigError, MeshImportError
    from adv3d_runner.shapes.library import add_asset, load_or_new_library
    from adv3d_runner.shapes.mesh_io import import_vehicle

    src = tmp_path / "src" / "Toy Pack"
    src.mkdir(parents=True)
    _write_car_cm(src / "ToyCar.obj")
    reads = []

    def read(path):
        reads.append(path)
        return import_vehicle(path, up="+z", forward="+x")

    lib_path = tmp_path / "lib" / "library.json"
    library = load_or_new_library(lib_path)
    with pytest.raises(ConfigError, match="licence"):
        add_asset(library, lib_path, src / "ToyCar.obj", "sedan", read)
    (src / "LICENSE.txt").write_text("CC0 1.0 Universal\n")
    with pytest.raises(ConfigError, match="class"):
        add_asset(library, lib_path, src / "ToyCar.obj", "Sedan!", read)
    with pytest.raises(ConfigError, match="asset id"):
        add_asset(library, lib_path, src / "ToyCar.obj", "sedan", read, asset_id="Bad Id")
    with pytest.raises(MeshImportError, match="nothing.obj"):
        add_asset(library, lib_path, src / "nothing.obj", "sedan", read)
    assert reads == [] and not lib_path.exists()  # refused before any work, nothing written

    asset = add_asset(library, lib_path, src / "ToyCar.obj", "sedan", read, note="why", author="me")
    assert reads == [src / "ToyCar.obj"]
    assert (asset.id, asset.file) == ("toy-pack.toycar", "toy-pack/toycar.glb")
    assert asset.source == {"pack": "toy-pack", "file": "ToyCar.obj", "author": "me", "url": ""}
    assert asset.licence == {"name": "CC0-1.0", "file": "toy-pack/LICENSE.txt"}
    assert asset.curation["note"] == "why" and asset.in_shape_space
    assert load_library(lib_path).assets == [asset]
    assert load_asset_mesh(load_library(lib_path), asset.id).extents == pytest.approx(asset.dimensions, abs=1e-4)

    # a second id from the same file gets its own mesh file; the same id replaces in place
    other = add_asset(library, lib_path, src / "ToyCar.obj", "hatchback", read, asset_id="toy-pack.small",
                      in_shape_space=False)
    assert other.file == "toy-pack/small.glb" and (lib_path.parent / other.file).is_file()
    again = add_asset(library, lib_path, src / "ToyCar.obj", "suv", read)
    assert load_library(lib_path).ids() == ["toy-pack.toycar", "toy-pack.small"]
    assert load_library(lib_path).get("toy-pack.toycar") == again

    # the CLI runs the same pipeline: same record, same bytes
    cli_lib = tmp_path / "cli" / "library.json"
    assert main(["-q", "assets", "import", str(src / "ToyCar.obj"), "--class", "sedan", "--library", str(cli_lib),
                 "--up=+z", "--forward=+x", "--note", "why", "--author", "me"]) == 0
    assert load_library(cli_lib).assets == [asset]
    assert (cli_lib.parent / asset.file).read_bytes() == (tmp_path / "lib" / asset.file).read_bytes()
