"""PCA shape space: rank deficiency, determinism, file contract, decoding guarantees."""
from __future__ import annotations

import itertools
import json
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from adv3d_runner.cli import main as adv3d_main
from adv3d_runner.errors import ConfigError, EmptySurfaceError, FileFormatError, InvalidQueryError
from adv3d_runner.shapes.sdf import grid_for_dimensions, sdf_volume
from adv3d_runner.shapes.shape_space import (
    DEFAULT_SHAPE_SPACE,
    ShapeSpace,
    build_shape_space,
    fit_pca,
    shape_space_from_sdfs,
)

RES = 32


def box(extents, centre) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return b


def toy_car(length: float, width: float, height: float, cabin: float = 0.5, wheel: float = 0.3) -> trimesh.Trimesh:
    """Body + cabin + four wheels (overlapping parts, like CAD), origin at footprint centre."""
    hb = 0.55 * height
    body = box((length, width, hb - 0.15), (0, 0, 0.15 + (hb - 0.15) / 2))
    cab = box((length * cabin, width * 0.85, height - hb + 0.05), (-0.08 * length, 0, hb - 0.05 + (height - hb + 0.05) / 2))
    parts = [body, cab]
    for sx in (-1, 1):
        for sy in (-1, 1):
            w = trimesh.creation.cylinder(radius=wheel, height=0.2, sections=12)
            w.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
            w.apply_translation((sx * length * 0.32, sy * (width / 2 - 0.1), wheel))
            parts.append(w)
    return trimesh.util.concatenate(parts)


SPECS = {
    "sedan": (4.6, 1.8, 1.45),
    "hatch": (4.0, 1.7, 1.5),
    "suv": (4.8, 1.9, 1.75),
    "van": (5.1, 2.0, 1.95),
    "sports": (4.3, 1.85, 1.25),
}


@dataclass
class FakeAsset:
    id: str
    vehicle_class: str
    dimensions: tuple
    in_shape_space: bool = True


class FakeLibrary:
    def __init__(self, specs: dict):
        self.assets = [FakeAsset(k, k, v) for k, v in specs.items()]
        self.meshes = {k: toy_car(*v) for k, v in specs.items()}

    def shape_space_assets(self):
        return [a for a in self.assets if a.in_shape_space]


def loader(lib: FakeLibrary, asset_id: str) -> trimesh.Trimesh:
    return lib.meshes[asset_id]


@pytest.fixture(scope="module")
def library() -> FakeLibrary:
    return FakeLibrary(SPECS)


@pytest.fixture(scope="module")
def space(library) -> ShapeSpace:
    return build_shape_space(library, resolution=RES, k=3, progress=False, mesh_loader=loader)


# ------------------------------------------------------------------------- PCA and building


def test_pca_properties(space):
    assert space.k == 3 and space.rank == 3 and space.dim == 5
    c = space.components.astype(np.float64)
    assert np.allclose(c @ c.T, np.eye(3), atol=1e-5)
    ev = space.explained_variance
    assert np.all(np.diff(ev) <= 0) and 0 < space.explained_variance_ratio.sum() <= 1 + 1e-9
    # Sign convention: the largest-magnitude entry of each component is positive.
    idx = np.argmax(np.abs(c), axis=1)
    assert np.all(c[np.arange(3), idx] > 0)
    # Latents are the projections of the assets and span [min, max] exactly.
    assert np.array_equal(space.latent_min, space.latents.min(axis=0))
    assert np.array_equal(space.latent_max, space.latents.max(axis=0))
    assert np.all(space.latent_max > space.latent_min)


def test_asset_latents_are_encodings(space, library):
    for i, a in enumerate(library.assets):
        m = library.meshes[a.id]
        sdf = sdf_volume(m.vertices, m.faces, space.grid)
        assert np.allclose(space.encode(sdf), space.latents[i], atol=1e-9)
        u = space.asset_unit(a.id)
        assert space.nearest_asset(u) == a.id


def test_encode_decode_roundtrip(space):
    z = np.array([0.3, -0.2, 0.1]) * (space.latent_max - space.latent_min)
    assert np.allclose(space.encode(space.decode_sdf(z)), z, atol=1e-4)


def test_unit_latent_mapping(space):
    u = np.array([0.0, 0.5, 1.0, 0.0, 1.0])
    z, s = space.unit_to_latent(u)
    assert z[0] == space.latent_min[0] and z[2] == space.latent_max[2]
    assert np.allclose(s, [0.8, 1.3])
    assert np.allclose(space.latent_to_unit(z, s), u)
    with pytest.raises(ConfigError):
        space.latent_to_unit(space.latent_max + 1.0, (1.0, 1.0))


def test_common_scale_is_from_shape_space_assets(space, library):
    largest = max(max(v) for v in SPECS.values())
    assert space.grid.extent_m == pytest.approx(1.1 * largest, rel=1e-3)
    # Assets outside the shape space (a bus) do not size the grid.
    lib = FakeLibrary({**SPECS, "bus": (12.0, 2.5, 3.2)})
    lib.assets[-1].in_shape_space = False
    sp = build_shape_space(lib, resolution=16, k=2, progress=False, mesh_loader=loader)
    assert sp.grid.extent_m == pytest.approx(1.1 * largest, rel=1e-3)
    assert "bus" not in sp.asset_ids


def test_build_reports_progress_through_the_callback(library):
    """``on_progress(done, total)`` before each asset and at the end (the add-on's progress bar);
    the space is the same as without it."""
    calls = []
    sp = build_shape_space(library, resolution=16, k=2, progress=True, mesh_loader=loader,
                           on_progress=lambda done, total: calls.append((done, total)))
    n = len(library.shape_space_assets())
    assert calls == [(i, n) for i in range(n + 1)]
    plain = build_shape_space(library, resolution=16, k=2, progress=False, mesh_loader=loader)
    assert sp.to_bytes() == plain.to_bytes()


def test_rebuild_is_byte_identical(library, tmp_path):
    a = build_shape_space(library, resolution=RES, k=3, progress=False, mesh_loader=loader)
    b = build_shape_space(library, resolution=RES, k=3, progress=False, mesh_loader=loader)
    a.save(tmp_path / "a.npz")
    b.save(tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    # Load -> save round-trips exactly.
    c = ShapeSpace.load(tmp_path / "a.npz")
    c.save(tmp_path / "c.npz")
    assert (tmp_path / "c.npz").read_bytes() == (tmp_path / "a.npz").read_bytes()
    assert c.asset_ids == a.asset_ids and c.grid == a.grid
    assert np.array_equal(c.components, a.components) and np.array_equal(c.latents, a.latents)


def test_duplicated_assets_rank_deficient(library, tmp_path):
    ids = ["sedan", "sedan_copy", "hatch", "hatch_copy"]
    grid = grid_for_dimensions([SPECS["sedan"], SPECS["hatch"]], RES)
    s = sdf_volume(library.meshes["sedan"].vertices, library.meshes["sedan"].faces, grid)
    h = sdf_volume(library.meshes["hatch"].vertices, library.meshes["hatch"].faces, grid)
    sdfs = np.stack([s, s, h, h])
    sp = shape_space_from_sdfs(sdfs, ids, grid, k=3)
    assert sp.rank == 1 and sp.k == 3
    for arr in (sp.mean, sp.components, sp.latents, sp.explained_variance, sp.explained_variance_ratio):
        assert np.all(np.isfinite(arr))
    c = sp.components.astype(np.float64)
    assert np.allclose(c @ c.T, np.eye(3), atol=1e-5)
    assert np.all(sp.explained_variance[1:] == 0) and np.all(sp.latent_min[1:] == sp.latent_max[1:])
    assert sp.latents[0, 0] == sp.latents[1, 0] and sp.latents[2, 0] == sp.latents[3, 0]
    again = shape_space_from_sdfs(sdfs.copy(), ids, grid, k=3)
    assert sp.to_bytes() == again.to_bytes()
    mesh = sp.decode([0.5, 0.0, 1.0, 0.5, 0.5])
    assert mesh.is_watertight and mesh.volume > 0
    # Zero-range dimensions map back to 0.5.
    assert np.allclose(sp.latent_to_unit(sp.latents[0], (1.0, 1.0))[1:3], 0.5)


def test_one_asset_library(library):
    lib = FakeLibrary({"sedan": SPECS["sedan"]})
    sp = build_shape_space(lib, resolution=RES, k=3, progress=False, mesh_loader=loader)
    assert sp.rank == 0 and sp.k == 3
    assert np.all(sp.latents == 0) and np.all(sp.latent_min == 0) and np.all(sp.latent_max == 0)
    assert np.all(sp.explained_variance == 0) and np.all(np.isfinite(sp.explained_variance_ratio))
    for u in ([0, 0, 0, 0.4, 0.4], [1, 1, 1, 0.4, 0.4]):
        mesh = sp.decode(u)
        assert mesh.is_watertight
        # Scales 1.0 (u=0.4): the decoded car has the asset's length and width within a voxel.
        vox = sp.grid.extent_m * sp.grid.voxel
        assert np.allclose(mesh.extents[:2], SPECS["sedan"][:2], atol=1.5 * vox)


def test_fit_pca_rejects_bad_k():
    with pytest.raises(ConfigError):
        fit_pca(np.zeros((2, 8)), 0)
    with pytest.raises(ConfigError):
        fit_pca(np.zeros((0, 8)), 1)


def test_fit_pca_is_the_svd_of_the_centred_data_with_fixed_signs():
    # fit_pca works through the small Gram matrix (its bits are pinned by the shipped shape
    # space); the result is the plain SVD's up to rounding, with the documented sign rule
    x = np.random.default_rng(5).standard_normal((7, 300)).astype(np.float32)
    mean, comps, var, ratio, rank = fit_pca(x, 4)
    xc = x.astype(np.float64) - x.astype(np.float64).mean(axis=0)
    _, s, vt = np.linalg.svd(xc, full_matrices=False)
    assert rank == 4 and np.allclose(mean, x.mean(axis=0, dtype=np.float64), rtol=0, atol=1e-12)
    assert np.allclose(var, s[:4] ** 2 / 6, rtol=1e-12, atol=0)
    assert np.allclose(ratio, s[:4] ** 2 / np.sum(s ** 2), rtol=1e-12, atol=0)
    signs = np.sign(vt[np.arange(4), np.argmax(np.abs(vt[:4]), axis=1)])
    assert np.allclose(comps, vt[:4] * signs[:, None], rtol=0, atol=1e-12)
    assert np.all(comps[np.arange(4), np.argmax(np.abs(comps), axis=1)] > 0)


# ------------------------------------------------------------------------------- decoding


def test_decode_every_corner_of_latent_box(space):
    vox = space.grid.extent_m * space.grid.voxel
    for corner in itertools.product((0.0, 1.0), repeat=space.dim):
        v, f = space.decode_arrays(corner)
        assert v.dtype == np.float64 and f.dtype == np.int64 and v.shape[1] == 3 and f.shape[1] == 3
        mesh = trimesh.Trimesh(v, f, process=False)
        assert mesh.is_watertight, corner
        assert mesh.is_winding_consistent, corner
        assert mesh.volume > 0, corner  # outward normals
        assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
        assert mesh.area_faces.min() > 1e-10, corner
        assert len(mesh.nondegenerate_faces()) == len(f)
        # Origin convention: lowest point on the ground, footprint centred.
        lo, hi = v.min(axis=0), v.max(axis=0)
        assert abs(lo[2]) < 1e-9
        assert np.allclose((lo[:2] + hi[:2]) / 2, 0, atol=1e-9)
        # A plausible car: 3-7 m long, narrower than long, lower than 2.5 m.
        assert 3.0 < hi[0] - lo[0] < 7.0 and hi[1] - lo[1] < hi[0] - lo[0] and hi[2] < 2.5 + vox


def test_width_and_length_scales(space):
    base = space.decode([0.5, 0.5, 0.5, 0.0, 0.0]).extents
    big = space.decode([0.5, 0.5, 0.5, 1.0, 1.0]).extents
    assert big[0] / base[0] == pytest.approx(1.3 / 0.8, rel=1e-6)
    assert big[1] / base[1] == pytest.approx(1.3 / 0.8, rel=1e-6)
    assert big[2] == pytest.approx(base[2], rel=1e-9)
    wide = space.decode([0.5, 0.5, 0.5, 1.0, 0.0]).extents
    assert wide[1] > base[1] and wide[0] == pytest.approx(base[0])


@pytest.mark.parametrize(
    "u, match",
    [
        ([0.5, 0.5, float("nan"), 0.5, 0.5], "NaN"),
        ([0.5, 0.5, float("inf"), 0.5, 0.5], "NaN or infinite"),
        ([0.5, 0.5, 0.5, 0.5], "5 entries"),
        ([0.5] * 6, "5 entries"),
        ([[0.5] * 5], "5 entries"),
        ([0.5, 1.2, 0.5, 0.5, 0.5], "entry 1"),
        ([0.5, 0.5, 0.5, 0.5, -0.01], "entry 4"),
        (["a", 0.5, 0.5, 0.5, 0.5], "unit vector"),
    ],
)
def test_bad_unit_vectors(space, u, match):
    with pytest.raises(ConfigError, match=match):
        space.decode_arrays(u)


def _constant_direction_space(space: ShapeSpace) -> ShapeSpace:
    """Component 0 = uniform offset of the whole field (a dilation direction)."""
    d = space.mean.size
    comps = space.components.copy()
    comps[0] = 1.0 / np.sqrt(d)
    return replace(space, components=comps)


def test_empty_level_set_raises_typed_error(space):
    sp = _constant_direction_space(space)
    big = 2.0 * space.grid.truncation * np.sqrt(space.mean.size)
    with pytest.raises(EmptySurfaceError, match="no surface") as info:
        sp.decode_latent([big, 0.0, 0.0])  # all outside
    assert isinstance(info.value, InvalidQueryError)
    with pytest.raises(EmptySurfaceError):
        sp.decode_latent([-big, 0.0, 0.0])  # all inside
    # Still a surface close to the mean.
    v, f = sp.decode_latent([0.0, 0.0, 0.0])
    assert len(f) > 0


# ------------------------------------------------------------------------------- file contract


def _rewrite(src: Path, dst: Path, edit) -> None:
    with np.load(src, allow_pickle=False) as npz:
        members = {k: npz[k] for k in npz.files}
    edit(members)
    with zipfile.ZipFile(dst, "w") as zf:
        for name, arr in members.items():
            with zf.open(f"{name}.npy", "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)


def test_load_rejects_bad_files(space, tmp_path):
    good = space.save(tmp_path / "good.npz")
    cases = {
        "$": lambda p: p.write_bytes(b"not a zip file at all"),
    }
    for fieldname, make in cases.items():
        bad = tmp_path / "corrupt.npz"
        make(bad)
        with pytest.raises(FileFormatError) as info:
            ShapeSpace.load(bad)
        assert info.value.field == fieldname and "corrupt.npz" in str(info.value)
    with pytest.raises(FileFormatError, match="file not found"):
        ShapeSpace.load(tmp_path / "missing.npz")

    def meta_edit(key, value):
        def edit(m):
            meta = json.loads(str(m["meta"]))
            meta[key] = value
            m["meta"] = np.asarray(json.dumps(meta))
        return edit

    edits = {
        "$.components": lambda m: m.pop("components"),
        "$.mean": lambda m: m.__setitem__("mean", m["mean"].astype(np.float64)),
        "$.latents": lambda m: m.__setitem__("latents", m["latents"][:, :2]),
        "$.meta.format": meta_edit("format", "something.else"),
        "$.meta.version": meta_edit("version", 99),
        "$.meta.k": meta_edit("k", "three"),
        "$.meta.latent_max": meta_edit("latent_max", [-1e5, -1e5, -1e5]),  # below latent_min
        "$.meta.latent_min[0]": meta_edit("latent_min", [-1e9, -1e9, -1e9]),  # beyond the contract's bound
        "$.meta.scale_range[1]": meta_edit("scale_range", [0.8, 1e12]),      # a 5e11 m car
        "$.meta.content_hash": lambda m: m.__setitem__("mean", m["mean"] + np.float32(1e-3)),
    }
    for fieldname, edit in edits.items():
        bad = tmp_path / "edited.npz"
        _rewrite(good, bad, edit)
        with pytest.raises(FileFormatError) as info:
            ShapeSpace.load(bad)
        assert info.value.field == fieldname, (fieldname, str(info.value))
        assert "edited.npz" in str(info.value)


def test_npz_has_fixed_timestamps(space, tmp_path):
    path = space.save(tmp_path / "s.npz")
    with zipfile.ZipFile(path) as zf:
        assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in zf.infolist())
        assert [i.filename for i in zf.infolist()] == ["meta.npy", "mean.npy", "components.npy", "latents.npy", "asset_ids.npy"]


# ------------------------------------------------------------------------------- CLI, shipped


def test_cli_decode_and_info(space, tmp_path, capsys):
    sp_path = space.save(tmp_path / "space.npz")
    out = tmp_path / "car.glb"
    rc = adv3d_main(["-q", "shapes", "decode", "--u", "0.5,0.5,0.5,0.5,0.5", "-o", str(out), "--space", str(sp_path)])
    assert rc == 0 and out.stat().st_size > 0
    loaded = trimesh.load(out, force="mesh")
    assert len(loaded.faces) > 0
    # glTF is y-up: the file's y extent is the car's height, read back in the library frame.
    from adv3d_runner.shapes.mesh_io import read_library_mesh

    back = read_library_mesh(out)
    ref = space.decode([0.5] * 5)
    assert np.allclose(back.bounds, ref.bounds, atol=1e-5)
    for suffix in (".obj", ".ply", ".stl"):
        rc = adv3d_main(["-q", "shapes", "decode", "--u", "0,1,0,1,0", "-o", str(tmp_path / f"car{suffix}"),
                         "--space", str(sp_path)])
        assert rc == 0 and (tmp_path / f"car{suffix}").stat().st_size > 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:  # refused by the argument type (argtypes.numbers): a usage error
        adv3d_main(["shapes", "decode", "--u", "0.5,0.5,nan,0.5,0.5", "-o", str(tmp_path / "x.glb"), "--space", str(sp_path)])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--u" in err and "'nan'" in err and not (tmp_path / "x.glb").exists()
    with pytest.raises(SystemExit) as exc:  # -o names no mesh format we write: a usage error
        adv3d_main(["shapes", "decode", "--u", "0.5,0.5,0.5,0.5,0.5", "-o", str(tmp_path / "x.fbx"), "--space", str(sp_path)])
    assert exc.value.code == 2
    rc = adv3d_main(["shapes", "info", "--space", str(sp_path)])
    out_txt = capsys.readouterr().out
    assert rc == 0 and "32^3" in out_txt and "sedan" in out_txt and space.content_hash in out_txt


def test_shipped_shape_space_loads_and_decodes():
    assert DEFAULT_SHAPE_SPACE.exists(), f"no shipped shape space at {DEFAULT_SHAPE_SPACE}"
    sp = ShapeSpace.load()
    assert sp.k == 3 and len(sp.asset_ids) >= 2 and sp.rank == 3
    assert sp.grid.resolution == 64 and sp.method == "winding"
    for corner in itertools.product((0.0, 1.0), repeat=sp.dim):
        mesh = sp.decode(corner)
        assert mesh.is_watertight and mesh.volume > 0, corner
        assert mesh.area_faces.min() > 1e-10, corner
        assert 2.5 < mesh.extents[0] < 8.0 and abs(mesh.bounds[0, 2]) < 1e-9, corner


def test_shipped_shape_space_matches_shipped_library():
    """The shipped space was built from exactly the library's shape-space vehicles, and its
    common scale is 1.1 x their largest dimension."""
    from adv3d_runner.shapes.library import load_library

    from adv3d_runner.shapes.library import load_asset_mesh
    from adv3d_runner.shapes.shape_space import library_fingerprint

    lib = load_library()
    sp = ShapeSpace.load()
    assets = lib.shape_space_assets()
    assert sp.asset_ids == [a.id for a in assets], "shipped shape space is stale: run `adv3d shapes build`"
    largest = max(max(a.dimensions) for a in assets)
    assert sp.grid.extent_m == pytest.approx(1.1 * largest, rel=0.02)
    meshes = [load_asset_mesh(lib, a.id) for a in assets]
    assert sp.build["library_fingerprint"] == library_fingerprint(assets, meshes), (
        "the library changed since the shipped shape space was built: run `adv3d shapes build`")


@pytest.mark.slow
def test_rebuilding_shipped_shape_space_is_byte_identical(tmp_path, repo_root):
    """``adv3d shapes build`` in the documented environment (docs/shape_space.md): the PCA's
    last bits depend on the OpenBLAS kernel, so the rebuild runs in a child process with
    OpenBLAS's generic x86-64 kernel (``OPENBLAS_CORETYPE=Prescott``) and one thread."""
    import os
    import subprocess
    import sys

    out = tmp_path / "vehicles_64.npz"
    env = {**os.environ, "OPENBLAS_CORETYPE": "Prescott", "OMP_NUM_THREADS": "1", "PYTHONPATH": str(repo_root)}
    proc = subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "-q", "shapes", "build", "--out", str(out)],
                          cwd=repo_root, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes() == DEFAULT_SHAPE_SPACE.read_bytes()


def test_decode_drops_crumbs_and_cavities():
    """Tiny detached parts and internal cavities (PCA-blend artefacts) are removed; a real
    second part is kept."""
    from adv3d_runner.shapes.decode import extract_surface
    from adv3d_runner.shapes.sdf import GridSpec

    grid = GridSpec(40, 5.0, -0.15, 0.1)
    p = grid.points()

    def box_field(c, half):
        q = np.abs(p - np.asarray(c)) - np.asarray(half)
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)

    body = box_field((0, 0, 0), (0.35, 0.15, 0.1))
    crumb = box_field((0, 0, 0.3), (0.02, 0.02, 0.02))
    cavity = -box_field((0.1, 0, 0), (0.03, 0.03, 0.03))
    second = box_field((0, 0.35, 0), (0.1, 0.1, 0.1))
    field = np.minimum(np.minimum(body, crumb), second)
    field = np.maximum(field, cavity).reshape((40,) * 3).astype(np.float32)
    raw_info: dict = {}
    raw = trimesh.Trimesh(*extract_surface(field, grid, min_part_fraction=0.0, info=raw_info), process=False)
    assert len(raw.split(only_watertight=False)) == 4
    assert raw_info["parts"] == 4 and raw_info["dropped_parts"] == 0 and raw_info["kept_parts"] == 4
    info: dict = {}
    clean = trimesh.Trimesh(*extract_surface(field, grid, info=info), process=False)
    parts = clean.split(only_watertight=False)
    assert len(parts) == 2 and all(part.volume > 0 for part in parts)
    assert clean.is_watertight and clean.volume > raw.volume  # the cavity no longer subtracts
    # what was dropped is counted and measured, not hidden
    assert info["parts"] == 4 and info["dropped_parts"] == 1 and info["dropped_cavities"] == 1
    assert info["kept_parts"] == 2
    small = sorted(abs(part.volume) for part in raw.split(only_watertight=False))[:2]  # crumb, cavity
    assert info["dropped_volume_m3"] == pytest.approx(sum(small), rel=1e-9)
    assert info["volume_m3"] == pytest.approx(clean.volume, rel=1e-9)


def test_decode_places_the_body_by_its_footprint_not_a_blob(caplog):
    """A blob beside the body (kept: over 1 % of its volume) must not shift the car: the
    footprint centre is the body's, and the drop of a crumb is logged."""
    import logging

    from adv3d_runner.shapes.decode import extract_surface
    from adv3d_runner.shapes.sdf import GridSpec

    grid = GridSpec(48, 6.0, -0.15, 0.1)
    p = grid.points()

    def box_field(c, half):
        q = np.abs(p - np.asarray(c)) - np.asarray(half)
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)

    body = box_field((0.0, 0.0, 0.0), (0.38, 0.15, 0.11))
    plain = extract_surface(body.reshape((48,) * 3).astype(np.float32), grid)[0]
    blob = box_field((0.0, 0.27, -0.05), (0.05, 0.05, 0.05))  # 3 % of the body, off to the left
    crumb = box_field((0.2, -0.3, 0.0), (0.012, 0.012, 0.012))
    field = np.minimum(np.minimum(body, blob), crumb).reshape((48,) * 3).astype(np.float32)
    info: dict = {}
    with caplog.at_level(logging.INFO, logger="adv3d_runner.shapes.decode"):
        v, f = extract_surface(field, grid, info=info)
    assert info["kept_parts"] == 2 and info["dropped_parts"] == 1
    assert "dropped 1 small part" in caplog.text
    body_v = v[v[:, 1] < 0.15 * 6.0 + 1e-6]
    # the body sits where it sits without the blob; the blob widens the mesh on one side only
    assert np.allclose([body_v[:, 0].min() + body_v[:, 0].max(), body_v[:, 1].min() + body_v[:, 1].max()], 0, atol=1e-9)
    assert np.allclose(body_v[:, 1].min(), plain[:, 1].min()) and v[:, 1].max() > plain[:, 1].max() + 0.5
