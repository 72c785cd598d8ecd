"""Mesh cleaning: each hard case is built so the test fails if cleaning or its report is wrong."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from adv3d_runner.shapes.cleaning import clean_mesh, edge_topology, face_components, mesh_report, orient_faces


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
