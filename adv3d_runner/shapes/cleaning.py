"""Mesh cleaning for the vehicle library, with a report of what the mesh was like.

Cleaning is deliberately conservative: it removes what is *wrong* (duplicate vertices,
zero-area and repeated triangles, unused vertices, faces wound against their neighbours) and
reports what is merely *open* (boundary edges, non-manifold edges, several components). It
never tries to close a mesh: the SDF builder uses a generalised-winding-number inside test
that copes with open bodies, interiors and self-intersections, but that test does need
consistently oriented faces, which is why orientation is repaired here.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np


def edge_topology(faces: np.ndarray) -> dict:
    """Counts of boundary, manifold and non-manifold edges and of inconsistent windings.

    Args:
        faces: (m, 3) int triangle indices.

    Returns:
        ``{"edges", "boundary_edges", "non_manifold_edges", "inconsistent_edges"}``: undirected
        edges used by one face, by more than two faces, and manifold edges whose two faces run
        the edge in the same direction (their normals disagree).
    """
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return {"edges": 0, "boundary_edges": 0, "non_manifold_edges": 0, "inconsistent_edges": 0}
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    # on a manifold edge the two faces run it in opposite directions when consistently wound
    forward = (directed[:, 0] < directed[:, 1]).astype(np.int64)
    n_forward = np.bincount(inverse, weights=forward, minlength=len(counts))
    manifold = counts == 2
    inconsistent = manifold & (n_forward != 1)
    return {
        "edges": int(len(counts)),
        "boundary_edges": int(np.sum(counts == 1)),
        "non_manifold_edges": int(np.sum(counts > 2)),
        "inconsistent_edges": int(np.sum(inconsistent)),
    }


def _manifold_pairs(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face pairs sharing a manifold edge, and whether they run it in the same direction."""
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    face_of = np.repeat(np.arange(len(faces)), 3)
    undirected = np.sort(directed, axis=1)
    order = np.lexsort((undirected[:, 1], undirected[:, 0]))
    su = undirected[order]
    same_as_next = np.all(su[1:] == su[:-1], axis=1)
    # keep runs of exactly two: equal to the next, and the next is not equal to the one after
    starts = np.flatnonzero(same_as_next)
    run_of_two = np.ones(len(starts), dtype=bool)
    nxt = starts + 1
    run_of_two &= ~np.isin(nxt, starts)  # not followed by a third copy
    run_of_two &= ~np.isin(starts - 1, starts)  # not preceded by an equal copy
    a, b = order[starts[run_of_two]], order[nxt[run_of_two]]
    same_direction = np.all(directed[a] == directed[b], axis=1)
    return np.stack([face_of[a], face_of[b]], axis=1), same_direction


def face_components(faces: np.ndarray) -> np.ndarray:
    """Component label per face (faces sharing an edge or a vertex are connected).

    Returns:
        (m,) int labels 0..k-1, numbered in order of each component's first face.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    m = len(faces)
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    n_vertices = int(faces.max()) + 1
    rows = np.repeat(np.arange(m), 3)
    # bipartite face-vertex graph: faces are connected through shared vertices
    graph = coo_matrix((np.ones(3 * m), (rows, m + faces.reshape(-1))), shape=(m + n_vertices, m + n_vertices))
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[:m]
    _, first, relabel = np.unique(face_labels, return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))  # renumber by first appearance: deterministic
    return rank[relabel.reshape(-1)]


def orient_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Make windings consistent across manifold edges, then point each part outwards.

    A breadth-first walk over each edge-connected patch flips faces whose shared edge runs the
    same way as their neighbour's, keeping the orientation most of the patch already has. A *closed* patch (no boundary edge,
    >= 4 faces) whose signed volume is negative is then flipped as a whole. Open patches keep
    the orientation of their first face: for them the volume sign is not evidence (a wheel's
    recessed hub is a concave, correctly outward dish with negative volume about its centroid).

    Returns:
        (faces with corrected winding, number of faces flipped).
    """
    faces = np.asarray(faces, dtype=np.int64).copy()
    m = len(faces)
    if m == 0:
        return faces, 0
    pairs, same = _manifold_pairs(faces)
    neighbours: list[list[tuple[int, bool]]] = [[] for _ in range(m)]
    for (a, b), s in zip(pairs.tolist(), same.tolist()):
        neighbours[a].append((b, s))
        neighbours[b].append((a, s))
    flip = np.zeros(m, dtype=bool)
    patch = np.full(m, -1, dtype=np.int64)
    n_patches = 0
    for seed in range(m):
        if patch[seed] >= 0:
            continue
        patch[seed] = n_patches
        queue = deque([seed])
        while queue:
            f = queue.popleft()
            for g, s in neighbours[f]:
                if patch[g] < 0:
                    patch[g] = n_patches
                    flip[g] = flip[f] ^ s  # same direction on a shared edge: opposite winding
                    queue.append(g)
        n_patches += 1
    # keep the majority orientation of each patch: change as few faces as possible, so a
    # small mis-wound piece never turns a whole body inside out because its index came first
    patch_size = np.bincount(patch, minlength=n_patches)
    patch_flips = np.bincount(patch, weights=flip, minlength=n_patches)
    flip ^= (2 * patch_flips > patch_size)[patch]
    original = faces.copy()
    faces[flip] = faces[flip][:, ::-1]
    # a patch that cannot be oriented (joined through a twisted strip) may get worse: keep
    # any patch whose own count of inconsistent edges did not go down
    for p in np.unique(patch[flip]):
        idx = np.flatnonzero(patch == p)
        if edge_topology(faces[idx])["inconsistent_edges"] >= edge_topology(original[idx])["inconsistent_edges"]:
            faces[idx] = original[idx]
            flip[idx] = False
    # outwards: signed volume of each patch about its own centroid
    tri = np.asarray(vertices, dtype=np.float64)[faces]
    for p in range(n_patches):
        idx = np.flatnonzero(patch == p)
        if len(idx) < 4 or edge_topology(faces[idx])["boundary_edges"] > 0:
            continue
        t = tri[idx] - tri[idx].reshape(-1, 3).mean(axis=0)
        volume = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0
        if volume < 0:
            faces[idx] = faces[idx][:, ::-1]
            flip[idx] = ~flip[idx]
    return faces, int(np.sum(flip))


def mesh_report(mesh) -> dict:
    """Topology report of a mesh without changing it (see :func:`clean_mesh`)."""
    faces = np.asarray(mesh.faces, dtype=np.int64)
    topo = edge_topology(faces)
    labels = face_components(faces)
    watertight = topo["boundary_edges"] == 0 and topo["non_manifold_edges"] == 0 and len(faces) > 0
    return {
        "triangles": int(len(faces)),
        "vertices": int(len(mesh.vertices)),
        "components": int(labels.max() + 1) if len(labels) else 0,
        "boundary_edges": topo["boundary_edges"],
        "non_manifold_edges": topo["non_manifold_edges"],
        "inconsistent_edges": topo["inconsistent_edges"],
        "watertight": bool(watertight),
    }


def clean_mesh(mesh, fix_orientation: bool = True) -> tuple[Any, dict]:
    """Clean a triangle mesh and report what was found.

    Steps: merge coincident vertices; drop degenerate faces (repeated index or zero area);
    drop duplicate faces (same three vertices in any order or orientation); drop unreferenced
    vertices; optionally make face orientation consistent and outward (:func:`orient_faces`).
    The mesh is NOT closed: open bodies stay open.

    Args:
        mesh: ``trimesh.Trimesh`` (not modified).
        fix_orientation: repair windings (needed by winding-number inside tests).

    Returns:
        (clean mesh, report) where the report holds ints/bools only: ``triangles_in``,
        ``merged_vertices``, ``degenerate_faces_removed``, ``duplicate_faces_removed``,
        ``unreferenced_vertices_removed``, ``inconsistent_edges_before``, ``faces_flipped``,
        then :func:`mesh_report` of the result (``triangles``, ``vertices``, ``components``,
        ``boundary_edges``, ``non_manifold_edges``, ``inconsistent_edges``, ``watertight``).
    """
    import trimesh

    out = mesh.copy()
    triangles_in = len(out.faces)
    n_vertices = len(out.vertices)
    out.merge_vertices(merge_tex=True, merge_norm=True)
    merged = n_vertices - len(out.vertices)

    faces = np.asarray(out.faces, dtype=np.int64)
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
    tri = np.asarray(out.vertices, dtype=np.float64)[faces]
    doubled_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    # zero area: relative to the squared longest edge, so it works in any unit
    longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    degenerate = repeated | (doubled_area <= 1e-12 * np.maximum(longest ** 2, 1e-300))
    out.update_faces(~degenerate)

    faces = np.asarray(out.faces, dtype=np.int64)
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    keep = np.zeros(len(faces), dtype=bool)
    keep[first] = True  # keep the first copy, in file order
    duplicates = int(np.sum(~keep))
    out.update_faces(keep)

    n_before = len(out.vertices)
    out.remove_unreferenced_vertices()
    unreferenced = n_before - len(out.vertices)

    inconsistent_before = edge_topology(out.faces)["inconsistent_edges"]
    flipped = 0
    if fix_orientation and len(out.faces):
        new_faces, flipped = orient_faces(out.vertices, out.faces)
        colours = out.visual.face_colors.copy() if out.visual.kind == "face" else None
        out = trimesh.Trimesh(out.vertices, new_faces, process=False)
        if colours is not None:
            out.visual = trimesh.visual.ColorVisuals(out, face_colors=colours)

    report = {
        "triangles_in": int(triangles_in),
        "merged_vertices": int(merged),
        "degenerate_faces_removed": int(np.sum(degenerate)),
        "duplicate_faces_removed": duplicates,
        "unreferenced_vertices_removed": int(unreferenced),
        "inconsistent_edges_before": int(inconsistent_before),
        "faces_flipped": int(flipped),
    }
    report.update(mesh_report(out))
    return out, report
