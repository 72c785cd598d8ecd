"""Mesh cleaning: each hard case is built so the test fails if cleaning or its report is wrong."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from adv3d_runner.errors import ConfigError
from adv3d_runner.shapes.cleaning import (
    ORIENT_RULES,
    _connected_vertex_parts_numpy,
    clean_mesh,
    connected_vertex_parts,
    edge_topology,
    face_components,
    mesh_report,
    orient_faces,
)


def box(extents=(4.0, 2.0, 1.5), offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(offset)
    return m


def test_clean_box_is_untouched_and_watertight():
    clean, rep = clean_mesh(box())
    assert rep["triangles"] == 12 and rep["triangles_in"] == 12
    assert rep["watertight"] is True
    assert rep["boundary_edges"] == 0 and rep["non_manifold_edges"] == 0
    assert rep["components"] == 1
    assert rep["degenerate_faces_removed"] == 0 and rep["duplicate_faces_removed"] == 0
    assert rep["faces_flipped"] == 0
    assert clean.volume == pytest.approx(4.0 * 2.0 * 1.5)


def test_degenerate_and_duplicate_faces_removed_and_counted():
    m = box()
    v = np.vstack([m.vertices, [[10.0, 0, 0], [11.0, 0, 0], [12.0, 0, 0]]])  # three collinear points
    f = m.faces
    extra = np.array([
        [0, 0, 1],            # repeated index: degenerate
        [8, 9, 10],           # collinear: zero area
        f[3][[1, 2, 0]],      # same triangle as face 3, rotated: duplicate
        f[5][::-1],           # face 5 with opposite orientation: duplicate (double-sided)
        f[7],                 # exact copy: duplicate
    ])
    dirty = trimesh.Trimesh(v, np.vstack([f, extra]), process=False)
    clean, rep = clean_mesh(dirty)
    assert rep["triangles_in"] == 17
    assert rep["degenerate_faces_removed"] == 2
    assert rep["duplicate_faces_removed"] == 3
    assert rep["triangles"] == 12
    assert rep["unreferenced_vertices_removed"] == 3  # the collinear points are now unused
    assert rep["watertight"] is True
    assert clean.volume == pytest.approx(12.0)


def test_duplicate_vertices_are_merged_so_a_triangle_soup_box_is_closed():
    m = box()
    soup = trimesh.Trimesh(m.vertices[m.faces].reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False)
    assert mesh_report(soup)["boundary_edges"] == 36  # every edge open before merging
    clean, rep = clean_mesh(soup)
    assert rep["merged_vertices"] == 36 - 8
    assert rep["watertight"] is True and rep["vertices"] == 8


def test_open_body_is_reported_not_closed():
    m = box()
    top = np.flatnonzero(m.face_normals[:, 2] > 0.5)
    assert len(top) == 2
    open_box = trimesh.Trimesh(m.vertices, np.delete(m.faces, top, axis=0), process=False)
    clean, rep = clean_mesh(open_box)
    assert rep["boundary_edges"] == 4
    assert rep["watertight"] is False
    assert rep["triangles"] == 10  # not filled


def test_inconsistent_orientation_reported_and_repaired():
    m = box()
    faces = m.faces.copy()
    faces[[4, 7, 9]] = faces[[4, 7, 9]][:, ::-1]
    bad = trimesh.Trimesh(m.vertices, faces, process=False)
    assert edge_topology(bad.faces)["inconsistent_edges"] > 0
    clean, rep = clean_mesh(bad)
    assert rep["inconsistent_edges_before"] == edge_topology(faces)["inconsistent_edges"] > 0
    assert rep["inconsistent_edges"] == 0
    assert rep["faces_flipped"] == 3
    assert clean.volume == pytest.approx(12.0)  # outward again
    # without repair the problem is only reported
    _, rep2 = clean_mesh(bad, fix_orientation=False)
    assert rep2["inconsistent_edges"] == rep["inconsistent_edges_before"]


def test_inside_out_closed_part_is_turned_outward_per_component():
    a = box(offset=(0, 0, 0))
    b = box(extents=(1, 1, 1), offset=(5, 0, 0))
    b.invert()  # whole part inside out: consistent windings, negative volume
    both = trimesh.util.concatenate([a, b])
    clean, rep = clean_mesh(both)
    assert rep["components"] == 2
    assert rep["faces_flipped"] == 12
    labels = face_components(clean.faces)
    for k in range(2):
        part = trimesh.Trimesh(clean.vertices, clean.faces[labels == k], process=False)
        assert part.volume > 0


def test_open_part_orientation_is_kept():
    # an open dish facing "inward" is not evidence for flipping (wheel hubs are concave)
    m = box()
    top = np.flatnonzero(m.face_normals[:, 2] > 0.5)
    open_box = trimesh.Trimesh(m.vertices, np.delete(m.faces, top, axis=0)[:, ::-1], process=False)
    faces, flipped = orient_faces(open_box.vertices, open_box.faces)
    assert flipped == 0
    assert np.array_equal(faces, open_box.faces)


def test_non_manifold_edge_and_components_counted():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three faces on edge 0-1
    far = box(extents=(1, 1, 1), offset=(10, 0, 0))
    m = trimesh.util.concatenate([trimesh.Trimesh(v, fan, process=False), far])
    rep = mesh_report(m)
    assert rep["non_manifold_edges"] == 1
    assert rep["components"] == 2
    assert rep["watertight"] is False


def test_face_colours_follow_removed_faces():
    m = box()
    f = np.vstack([m.faces, m.faces[0]])  # duplicate of face 0 at the end
    colours = np.tile([10, 20, 30, 255], (13, 1)).astype(np.uint8)
    colours[5] = [200, 0, 0, 255]
    colours[12] = [0, 255, 0, 255]  # the duplicate's colour must disappear with it
    dirty = trimesh.Trimesh(m.vertices, f, face_colors=colours, process=False)
    clean, rep = clean_mesh(dirty)
    assert rep["duplicate_faces_removed"] == 1
    fc = np.asarray(clean.visual.face_colors)
    assert len(fc) == 12
    assert fc[5].tolist() == [200, 0, 0, 255]
    assert not np.any(np.all(fc == [0, 255, 0, 255], axis=1))


def test_clean_does_not_modify_input():
    m = box()
    m.faces[[1]] = m.faces[[1]][:, ::-1]
    before = m.faces.copy()
    clean_mesh(m)
    assert np.array_equal(m.faces, before)


def test_minority_of_mis_wound_faces_is_flipped_even_if_it_comes_first():
    # open box (no closed-body volume rule applies); face 0 is the odd one out
    m = box()
    top = np.flatnonzero(m.face_normals[:, 2] > 0.5)
    faces = np.delete(m.faces, top, axis=0)
    faces[0] = faces[0][::-1]
    fixed, flipped = orient_faces(m.vertices, faces)
    assert flipped == 1
    assert np.array_equal(fixed[0], faces[0][::-1]) and np.array_equal(fixed[1:], faces[1:])
    assert edge_topology(fixed)["inconsistent_edges"] == 0


def dish(inward: bool) -> trimesh.Trimesh:
    """An open bowl (lower cap of a sphere); ``inward``: normals face its concave side, as on a
    wheel's recessed hub seen from outside the vehicle."""
    s = trimesh.creation.icosphere(3)
    cap = s.faces[s.triangles_center[:, 2] < -0.3]
    return trimesh.Trimesh(s.vertices, cap[:, ::-1] if inward else cap, process=False)


def test_orientation_rules_differ_only_in_how_open_patches_face():
    assert ORIENT_RULES == ("majority", "outward")
    hub = dish(inward=True)
    # the library rule never flips an open patch: its volume sign is not evidence
    faces, flipped = orient_faces(hub.vertices, hub.faces, rule="majority")
    assert flipped == 0 and np.array_equal(faces, hub.faces)
    # the SDF rule turns every patch so its normals face away from the patch's own centroid
    faces, flipped = orient_faces(hub.vertices, hub.faces, rule="outward")
    assert flipped == len(hub.faces) and np.array_equal(faces, hub.faces[:, ::-1])
    bowl = dish(inward=False)
    assert orient_faces(bowl.vertices, bowl.faces, rule="outward")[1] == 0
    # on a closed inside-out part both rules agree
    inside_out = box()
    inside_out.invert()
    for rule in ORIENT_RULES:
        faces, flipped = orient_faces(inside_out.vertices, inside_out.faces, rule=rule)
        assert flipped == 12
        assert trimesh.Trimesh(inside_out.vertices, faces, process=False).volume == pytest.approx(12.0)


def test_unknown_orientation_rule_is_refused():
    with pytest.raises(ConfigError, match="majority"):
        orient_faces(box().vertices, box().faces, rule="winding")


def test_non_orientable_patch_is_not_made_worse():
    # a Moebius band: no orientation makes every edge consistent, one edge always stays wrong
    n, w = 24, 0.3
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rim = [np.stack([(1 + s * np.cos(t / 2)) * np.cos(t), (1 + s * np.cos(t / 2)) * np.sin(t), s * np.sin(t / 2)], 1)
           for s in (-w, w)]
    v = np.concatenate(rim)  # 0..n-1 one rim, n..2n-1 the other
    faces = []
    for i in range(n):
        c, d = (n, 0) if i == n - 1 else (i + 1, n + i + 1)  # the last quad joins the rims crosswise
        faces += [[i, n + i, d], [i, d, c]]
    faces = np.asarray(faces)
    faces[::3] = faces[::3, ::-1]
    before = edge_topology(faces)["inconsistent_edges"]
    fixed, flipped = orient_faces(v, faces)
    assert 0 < edge_topology(fixed)["inconsistent_edges"] < before
    assert flipped == int(np.sum(np.any(fixed != faces, axis=1)))


def test_faces_touching_at_one_vertex_are_one_component_numbered_by_first_face():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0]], float)
    faces = np.array([[5, 6, 7], [0, 1, 2], [0, 3, 4]])  # a lone face first, then a bow tie
    assert face_components(faces).tolist() == [0, 1, 1]
    assert mesh_report(trimesh.Trimesh(v, faces, process=False))["components"] == 2


def test_connected_parts_numpy_fallback_gives_scipys_labels():
    # Blender has no scipy: the add-on's cleaning and decoding take the numpy path
    rng = np.random.default_rng(3)
    n = 400
    edges = rng.integers(0, n, size=(300, 2))  # sparse random graph: many parts and singletons
    n_ref, ref = connected_vertex_parts(n, edges)
    n_np, got = _connected_vertex_parts_numpy(n, edges)
    assert n_np == n_ref > 10
    assert np.array_equal(got, ref)  # both number parts by their lowest vertex


_WITHOUT_SCIPY = """
import json, sys
for name in ("scipy", "networkx", "igl"):
    sys.modules[name] = None  # importing any of them now raises ImportError, as in Blender
sys.path.insert(0, "tests")
from test_cleaning import dirty_vehicle
from adv3d_runner.shapes.cleaning import clean_mesh
clean, report = clean_mesh(dirty_vehicle())
print(json.dumps({"report": report, "faces": clean.faces.tolist()}))
"""


def dirty_vehicle() -> trimesh.Trimesh:
    """Two parts (one inside out), a mis-wound face, a duplicate and an open hub."""
    body = box()
    body.faces[[2, 5]] = body.faces[[2, 5]][:, ::-1]
    wheel = box(extents=(0.6, 0.3, 0.6), offset=(1.2, 1.2, -0.5))
    wheel.invert()
    hub = dish(inward=True)
    hub.apply_scale(0.2)
    hub.apply_translation((1.2, 1.6, -0.5))
    m = trimesh.util.concatenate([body, wheel, hub])
    return trimesh.Trimesh(m.vertices, np.vstack([m.faces, m.faces[:1]]), process=False)


def test_cleaning_runs_without_scipy_networkx_or_libigl(repo_root):
    # a stock Blender has none of them, and the add-on cleans imported meshes in-process
    done = subprocess.run([sys.executable, "-c", _WITHOUT_SCIPY], cwd=repo_root, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)
    clean, report = clean_mesh(dirty_vehicle())
    assert got == {"report": report, "faces": clean.faces.tolist()}
    assert report["components"] == 3 and report["faces_flipped"] == 2 + 12
    assert report["duplicate_faces_removed"] == 1 and report["inconsistent_edges"] == 0
