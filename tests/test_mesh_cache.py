"""The content-keyed caches of derived data (docs/performance.md): library meshes
(shapes/mesh_cache.py) give what trimesh's glb reading gives, and a background's coherent-cast
certificates (sensors/coherent.py) what certifying it gives, bit for bit; both survive a corrupt
or foreign cache file."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.fileio import npz_bytes
from adv3d_runner.shapes import mesh_cache


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("ADV3D_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture(scope="module")
def assets():
    from adv3d_runner.shapes.library import load_library

    try:
        lib = load_library()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"bundled vehicle library not available: {exc}")
    ids = sorted(a.id for a in lib.assets)[:3]
    if not ids:
        pytest.skip("empty vehicle library")
    return lib, ids


def _trimesh_read(path):
    from adv3d_runner.shapes.mesh_io import read_library_mesh

    return read_library_mesh(path)


def _same(arrays, mesh):
    np.testing.assert_array_equal(arrays.vertices, np.asarray(mesh.vertices, np.float64))
    np.testing.assert_array_equal(arrays.faces, np.asarray(mesh.faces, np.int64))
    np.testing.assert_array_equal(arrays.bounds, mesh.bounds)
    assert arrays.vertices.dtype == np.float64 and arrays.faces.dtype == np.int64


def test_cached_arrays_equal_the_glb_read_on_miss_and_hit(cache, assets):
    lib, ids = assets
    for aid in ids:
        path = lib.path_of(aid)
        mesh = _trimesh_read(path)
        first = mesh_cache.library_mesh_arrays(path)  # miss: parsed and written
        target = mesh_cache.cache_path(path.read_bytes())
        assert target.is_file() and target.parent.parent == cache
        second = mesh_cache.library_mesh_arrays(path)  # hit: read from the npz
        _same(first, mesh)
        _same(second, mesh)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "faces_out_of_range", "wrong_bounds", "pickled"])
def test_a_corrupt_cache_file_is_ignored_and_rewritten(cache, assets, damage):
    lib, ids = assets
    path = lib.path_of(ids[0])
    good = mesh_cache.library_mesh_arrays(path)
    target = mesh_cache.cache_path(path.read_bytes())
    raw = target.read_bytes()
    if damage == "garbage":
        target.write_bytes(b"not a zip at all")
    elif damage == "truncated":
        target.write_bytes(raw[: len(raw) // 2])
    elif damage == "faces_out_of_range":
        target.write_bytes(npz_bytes({"vertices": good.vertices, "faces": good.faces + len(good.vertices),
                                      "bounds": good.bounds}))
    elif damage == "wrong_bounds":
        target.write_bytes(npz_bytes({"vertices": good.vertices, "faces": good.faces, "bounds": good.bounds + 1.0}))
    else:  # an object array needs pickle to load: refused
        import io
        import zipfile

        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for name in ("vertices", "faces", "bounds"):
                npy = io.BytesIO()
                np.lib.format.write_array(npy, np.array([{"x": 1}], dtype=object), allow_pickle=True)
                zf.writestr(f"{name}.npy", npy.getvalue())
        target.write_bytes(buf.getvalue())
    again = mesh_cache.library_mesh_arrays(path)
    _same(again, _trimesh_read(path))
    assert mesh_cache._load(target) is not None  # rewritten with good arrays


def test_the_key_follows_the_content(tmp_path, cache, assets):
    lib, ids = assets
    path = lib.path_of(ids[0])
    data = path.read_bytes()
    assert mesh_cache.cache_path(data) == mesh_cache.cache_path(bytes(data))
    assert mesh_cache.cache_path(data) != mesh_cache.cache_path(data + b"\0")


def test_missing_file_names_it(cache, tmp_path):
    from adv3d_runner.errors import MeshImportError

    with pytest.raises(MeshImportError, match="missing.glb"):
        mesh_cache.library_mesh_arrays(tmp_path / "missing.glb")


def test_actor_mesh_equals_the_trimesh_computation(cache, assets):
    """The simulator's actor meshes are the ones the glb read through trimesh gave."""
    from adv3d_runner.scene import actors

    lib, ids = assets
    dims = np.array([4.6, 1.9, 1.5])
    for aid in ids:
        mesh = _trimesh_read(lib.path_of(aid)).copy()
        lo, hi = mesh.bounds
        scale = dims / np.maximum(hi - lo, 1e-9)
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        expected = (np.asarray(mesh.vertices) - centre) * scale
        actors._MESH_CACHE.clear()
        got = actors.actor_mesh(lib, aid, dims)
        np.testing.assert_array_equal(got.vertices, expected)
        np.testing.assert_array_equal(got.faces, np.asarray(mesh.faces))


def _background():
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.background import background_mesh

    path = Path(__file__).resolve().parents[1] / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not path.exists():
        pytest.skip("bundled scene missing")
    v, f, _ = background_mesh(load_scene(path))
    return np.asarray(v, np.float32), np.asarray(f, np.int32)


def test_certificates_from_the_cache_equal_the_computed_ones(cache):
    from adv3d_runner.sensors import coherent

    v, f = _background()
    assert len(f) >= coherent.CACHE_MIN_FACES
    want = coherent.face_certificates(v, f)
    first = coherent.cached_face_certificates(v, f)  # computed and written
    path = coherent.certificates_cache_path(v, f)
    assert path.is_file()
    second = coherent.cached_face_certificates(v, f)  # read
    for got in (first, second):
        assert got.margin == want.margin
        for name in coherent._ARRAYS:
            a, b = getattr(got, name), getattr(want, name)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    moved = v.copy()
    moved[0, 0] += 1.0
    assert coherent.certificates_cache_path(moved, f) != path


@pytest.mark.parametrize("damage", ["garbage", "truncated", "slot_out_of_range"])
def test_a_corrupt_certificates_file_is_recomputed(cache, damage):
    from adv3d_runner.sensors import coherent

    v, f = _background()
    want = coherent.cached_face_certificates(v, f)
    path = coherent.certificates_cache_path(v, f)
    if damage == "garbage":
        path.write_bytes(b"PK not really")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:1000])
    else:
        members = {k: getattr(want, k) for k in coherent._ARRAYS}
        members["cell_slot"] = members["cell_slot"] + len(members["cell_frame"]) + 1
        path.write_bytes(npz_bytes(members))
    got = coherent.cached_face_certificates(v, f)
    for name in coherent._ARRAYS:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert coherent._load_certificates(path, len(f), coherent.MARGIN_M) is not False  # rewritten
