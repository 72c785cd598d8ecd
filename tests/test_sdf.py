"""Inside/outside and distance correctness of the SDF volumes on the hard cases of real CAD."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from adv3d_runner.errors import Adv3dError, ConfigError
from adv3d_runner.shapes.sdf import METHODS, GridSpec, grid_for_dimensions, sdf_volume

RES = 32
# One grid for every case: a 4 m cube edge with the ground plane near the bottom.
GRID = grid_for_dimensions([(3.6, 1.6, 1.6)], RES)


def box(extents, centre) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(centre)
    return b


def nodes_m() -> np.ndarray:
    """(N^3, 3) grid nodes in vehicle metres."""
    return GRID.to_metric(GRID.points())


def in_boxes(p: np.ndarray, boxes) -> np.ndarray:
    inside = np.zeros(len(p), dtype=bool)
    for ext, c in boxes:
        inside |= np.all(np.abs(p - np.asarray(c)) < np.asarray(ext) / 2, axis=1)
    return inside


def box_sdf(p: np.ndarray, ext, c) -> np.ndarray:
    """Exact SDF of one box, metres."""
    q = np.abs(p - np.asarray(c)) - np.asarray(ext) / 2
    outside = np.linalg.norm(np.maximum(q, 0), axis=1)
    inside = np.minimum(q.max(axis=1), 0)
    return outside + inside


def band(p: np.ndarray, boxes, width: float) -> np.ndarray:
    """Nodes within ``width`` metres of any box surface (sign there may legitimately wobble)."""
    near = np.zeros(len(p), dtype=bool)
    for ext, c in boxes:
        near |= np.abs(box_sdf(p, ext, c)) < width
    return near


BODY = ((3.0, 1.4, 0.8), (0.0, 0.0, 0.6))
CABIN = ((1.6, 1.2, 0.6), (-0.3, 0.0, 1.2))  # overlaps BODY in z 0.9..1.0


def sign_mismatch(sdf: np.ndarray, boxes) -> int:
    p = nodes_m()
    expected = in_boxes(p, boxes)
    got = sdf.ravel() < 0
    ok = band(p, boxes, 1e-3)
    return int(np.sum((expected != got) & ~ok))


@pytest.mark.parametrize("method", METHODS)
def test_closed_box_matches_exact_sdf(method):
    mesh = box(*BODY)
    sdf = sdf_volume(mesh.vertices, mesh.faces, GRID, method)
    assert sdf.shape == (RES,) * 3 and sdf.dtype == np.float32
    exact = np.clip(box_sdf(nodes_m(), *BODY) / GRID.extent_m, -GRID.truncation, GRID.truncation)
    err = np.abs(sdf.ravel() - exact)
    if method == "floodfill":
        # Sign is decided voxel-wise: nodes within the wall band next to the surface flip.
        far = np.abs(exact) > GRID.voxel
        assert err[far].max() < 1e-5
    else:
        assert err.max() < 1e-5


@pytest.mark.parametrize("method", METHODS)
def test_self_intersecting_union(method):
    """Two overlapping parts: the overlap is inside, and hidden faces inside the union do not
    create small |SDF| values there."""
    mesh = trimesh.util.concatenate([box(*BODY), box(*CABIN)])
    sdf = sdf_volume(mesh.vertices, mesh.faces, GRID, method)
    assert sign_mismatch(sdf, [BODY, CABIN]) == 0 if method != "floodfill" else True
    # A node near the hidden cabin floor (z = 0.9) but deep inside the union.
    p = nodes_m()
    inside_both = in_boxes(p, [BODY]) & (np.abs(p[:, 2] - 0.95) < GRID.voxel * GRID.extent_m)
    inside_both &= (np.abs(p[:, 0] + 0.3) < 0.2) & (np.abs(p[:, 1]) < 0.2)
    assert inside_both.any()
    if method != "floodfill":  # floodfill keeps the distance to hidden faces (the paper's tool does too)
        depth = -sdf.ravel()[inside_both] * GRID.extent_m
        assert np.all(depth > 0.3), depth  # ~0.4-0.55 m to the nearest outer face (wall at y=0.7)


@pytest.mark.parametrize("method", METHODS)
def test_interior_part_does_not_flip_sign(method):
    """A box inside a box (seats inside a body), interior oriented either way."""
    inner = ((1.0, 0.6, 0.3), (0.2, 0.0, 0.6))
    for flip_inner in (False, True):
        part = box(*inner)
        if flip_inner:
            part.invert()
        mesh = trimesh.util.concatenate([box(*BODY), part])
        sdf = sdf_volume(mesh.vertices, mesh.faces, GRID, method)
        if method == "floodfill":
            assert sign_mismatch(sdf, [BODY]) <= int(band(nodes_m(), [BODY], 0.75 * GRID.voxel * GRID.extent_m).sum())
        else:
            assert sign_mismatch(sdf, [BODY]) == 0
        p = nodes_m()
        in_inner = in_boxes(p, [inner])
        assert np.all(sdf.ravel()[in_inner] < 0)
        if method == "winding":
            # Distance ignores the interior part: nodes around it are as deep as in the plain box.
            plain = sdf_volume(*_arrays(box(*BODY)), GRID, method)
            assert np.allclose(sdf, plain, atol=1e-6)


def _arrays(mesh: trimesh.Trimesh):
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


@pytest.mark.parametrize("method", METHODS)
def test_inconsistent_orientation_same_sdf(method, rng):
    mesh = trimesh.util.concatenate([box(*BODY), box(*CABIN)])
    ref = sdf_volume(mesh.vertices, mesh.faces, GRID, method)
    faces = np.asarray(mesh.faces).copy()
    flip = rng.permutation(len(faces))[: len(faces) // 2]
    faces[flip] = faces[flip][:, ::-1]
    got = sdf_volume(mesh.vertices, faces, GRID, method)
    assert np.array_equal(ref < 0, got < 0)
    assert np.allclose(ref, got, atol=1e-6)


def test_fully_inverted_mesh_same_sdf():
    mesh = box(*BODY)
    ref = sdf_volume(mesh.vertices, mesh.faces, GRID)
    got = sdf_volume(mesh.vertices, np.asarray(mesh.faces)[:, ::-1], GRID)
    assert np.allclose(ref, got, atol=1e-6)


def windowed_body() -> trimesh.Trimesh:
    """The body box, subdivided, with two window openings cut in each side and one at the back."""
    mesh = box(*BODY).subdivide().subdivide().subdivide()
    c = mesh.triangles_center
    side = (np.abs(np.abs(c[:, 1]) - 0.7) < 1e-9) & (c[:, 2] > 0.4) & (c[:, 2] < 0.95)
    side &= ((c[:, 0] > -1.2) & (c[:, 0] < -0.2)) | ((c[:, 0] > 0.1) & (c[:, 0] < 1.1))
    back = (np.abs(c[:, 0] + 1.5) < 1e-9) & (c[:, 2] > 0.4) & (c[:, 2] < 0.95) & (np.abs(c[:, 1]) < 0.5)
    mesh.update_faces(~(side | back))
    mesh.remove_unreferenced_vertices()
    assert not mesh.is_watertight
    return mesh


def test_open_body_with_missing_windows_is_solid():
    mesh = windowed_body()
    sdf = sdf_volume(mesh.vertices, mesh.faces, GRID, "winding")
    p = nodes_m()
    inside = in_boxes(p, [BODY])
    # Every node of the body away from the openings is inside; the cabin behind the windows too.
    core = inside & ~band(p, [BODY], 0.2)
    assert np.all(sdf.ravel()[core] < 0)
    assert np.all(sdf.ravel()[~in_boxes(p, [((3.2, 1.6, 1.0), BODY[1])])] > 0)
    # The solid's volume stays close to the closed box (holes do not hollow it out).
    vox = (GRID.extent_m * GRID.voxel) ** 3
    vol = np.sum(sdf < 0) * vox
    assert abs(vol - 3.0 * 1.4 * 0.8) / (3.0 * 1.4 * 0.8) < 0.1


def test_floodfill_leaks_through_large_openings():
    """Documents why ``winding`` is the default: the flood fill walks in through the windows."""
    mesh = windowed_body()
    ff = sdf_volume(mesh.vertices, mesh.faces, GRID, "floodfill")
    wn = sdf_volume(mesh.vertices, mesh.faces, GRID, "winding")
    assert np.sum(ff < 0) < 0.8 * np.sum(wn < 0)


def test_duplicate_and_degenerate_faces_ignored():
    mesh = box(*BODY)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    ref = sdf_volume(v, f, GRID)
    extra = np.concatenate([f, f[:3], [[0, 0, 1], [2, 2, 2]]])
    # A zero-area sliver made of collinear points.
    v2 = np.concatenate([v, [[0, 0, 0.5], [0.1, 0, 0.5], [0.2, 0, 0.5]]])
    extra = np.concatenate([extra, [[len(v), len(v) + 1, len(v) + 2]]])
    got = sdf_volume(v2, extra, GRID)
    assert np.allclose(ref, got, atol=1e-6)


def test_mesh_outside_grid_rejected():
    big = box((6.0, 1.0, 1.0), (0, 0, 0.5))
    with pytest.raises(Adv3dError, match="does not fit"):
        sdf_volume(big.vertices, big.faces, GRID)


def test_flat_mesh_without_volume_rejected():
    quad_v = np.array([[-1, -0.5, 0.5], [1, -0.5, 0.5], [1, 0.5, 0.5], [-1, 0.5, 0.5]], float)
    quad_f = np.array([[0, 1, 2], [0, 2, 3]])
    with pytest.raises(Adv3dError, match="no volume"):
        sdf_volume(quad_v, quad_f, GRID)


def test_bad_method_and_grid():
    mesh = box(*BODY)
    with pytest.raises(ConfigError, match="unknown SDF method"):
        sdf_volume(mesh.vertices, mesh.faces, GRID, "magic")
    with pytest.raises(ConfigError):
        GridSpec(4, 1.0, 0.0)
    with pytest.raises(ConfigError):
        grid_for_dimensions([(4.0, float("nan"), 1.5)], 32)


def test_grid_common_scale_and_ground():
    g = grid_for_dimensions([(4.5, 1.8, 1.4), (5.0, 2.0, 1.9)], 64)
    assert g.extent_m == pytest.approx(1.1 * 5.0)
    # Tallest vehicle vertically centred: ground at -1.9 / 2 m.
    assert g.to_metric(np.array([[0.0, 0.0, 0.0]]))[0, 2] == pytest.approx(0.95)
    p = np.array([[1.0, -0.5, 0.3]])
    assert np.allclose(g.to_metric(g.to_unit(p)), p)


def double_walled_body(hole: bool = True) -> trimesh.Trimesh:
    """The body box as a shell: outer skin plus an inward-facing inner skin 8 cm inside,
    joined by a rim around a small opening in the roof, so both skins are one orientable
    patch (as in game/CAD models with interior trim). The winding number is ~0 in the hollow."""
    outer = box(*BODY).subdivide().subdivide().subdivide()
    v = np.asarray(outer.vertices)
    f = np.asarray(outer.faces)
    c = np.asarray(BODY[1])
    half = np.asarray(BODY[0]) / 2
    inner_v = c + (v - c) * (half - 0.08) / half
    centres = v[f].mean(axis=1)
    roof_cut = (np.abs(centres[:, 2] - 1.0) < 1e-9) & (np.abs(centres[:, 0] - 0.1) < 0.15) & (np.abs(centres[:, 1]) < 0.1)
    assert 0 < roof_cut.sum() <= 4
    keep = ~roof_cut if hole else np.ones(len(f), dtype=bool)
    n = len(v)
    faces = [f[keep], f[keep][:, ::-1] + n]
    if hole:
        # Boundary edges of the outer skin (a -> b as its faces run them) joined to the inner.
        e = np.concatenate([f[keep][:, [0, 1]], f[keep][:, [1, 2]], f[keep][:, [2, 0]]])
        key = {tuple(x) for x in e.tolist()}
        rim = [(a, b) for a, b in e.tolist() if (b, a) not in key]
        assert len(rim) >= 3
        faces += [np.array([[b, a, a + n], [b, a + n, b + n]]) for a, b in rim]
    mesh = trimesh.Trimesh(np.concatenate([v, inner_v]), np.concatenate(faces), process=False)
    return mesh


def test_double_walled_shell_is_filled_solid():
    mesh = double_walled_body()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    sdf = sdf_volume(mesh.vertices, mesh.faces, GRID, "winding")
    # Solid everywhere except, at most, a one-voxel dimple where the opening was.
    p = nodes_m()
    wrong = (in_boxes(p, [BODY]) != (sdf.ravel() < 0)) & ~band(p, [BODY], 1e-3)
    assert wrong.sum() <= 4
    assert np.all(np.abs(box_sdf(p[wrong], *BODY)) < GRID.voxel * GRID.extent_m)
    # Deep inside, the distance is to the outer skin, not to the (now interior) inner skin.
    plain = sdf_volume(*_arrays(box(*BODY)), GRID, "winding")
    core = in_boxes(nodes_m(), [((2.6, 1.0, 0.4), BODY[1])])
    assert np.all(sdf.ravel()[core] < -0.1 / GRID.extent_m)
    assert np.abs(sdf.ravel()[core] - plain.ravel()[core]).max() < 1.01 * GRID.voxel


def test_double_walled_shell_without_fill_would_be_hollow():
    """The fill step is what makes the shell solid: the raw winding number says 'outside'."""
    from adv3d_runner.shapes.cleaning import orient_faces
    from adv3d_runner.shapes.sdf import winding_numbers

    mesh = double_walled_body()
    v = GRID.to_unit(mesh.vertices)
    faces, _ = orient_faces(v, np.asarray(mesh.faces), rule="outward")  # the rule sdf_volume uses
    w = winding_numbers(v, faces, GRID.to_unit(np.array([[0.0, 0.0, 0.6]])))
    assert abs(w[0]) < 0.1
