# SPDX-License-Identifier: GPL-3.0-or-later
"""numpy <-> Blender mesh data, without per-element Python loops.

Everything goes through ``foreach_get`` / ``foreach_set`` on whole flat arrays (the fast path the
glTF importer uses); ``from_pydata`` is avoided because it walks Python lists.
"""
from __future__ import annotations

import bpy
import numpy as np


def mesh_arrays(mesh: "bpy.types.Mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and triangles (F, 3) int64 of a mesh (polygons triangulated).

    Quads and n-gons are fanned (Blender's ``loop_triangles`` does the triangulation).
    """
    n_vert = len(mesh.vertices)
    co = np.empty(n_vert * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    mesh.calc_loop_triangles()
    n_tri = len(mesh.loop_triangles)
    tris = np.empty(n_tri * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tris)
    return co.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3).astype(np.int64)


def _faces_of(mesh: "bpy.types.Mesh") -> np.ndarray | None:
    """The mesh's faces as (F, 3) when it is all triangles, else None."""
    n_poly = len(mesh.polygons)
    n_loop = len(mesh.loops)
    if n_loop != 3 * n_poly:
        return None
    idx = np.empty(n_loop, dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", idx)
    return idx.reshape(-1, 3)


def set_mesh_arrays(mesh: "bpy.types.Mesh", vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Put (V, 3) vertices and (F, 3) triangles into ``mesh`` in place.

    When the topology is unchanged only the vertex coordinates are written (one ``foreach_set``);
    otherwise the geometry is cleared and rebuilt with ``vertices.add`` / ``loops.add`` /
    ``polygons.add`` and three whole-array ``foreach_set`` calls.

    Returns:
        True when the topology was rebuilt, False when only positions changed.
    """
    verts = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    tris = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    if tris.size and (tris.min() < 0 or tris.max() >= len(verts)):
        raise ValueError("face index out of range")
    same = len(mesh.vertices) == len(verts) and len(mesh.polygons) == len(tris)
    if same:
        old = _faces_of(mesh)
        same = old is not None and np.array_equal(old, tris)
    if same:
        mesh.vertices.foreach_set("co", verts.ravel())
        mesh.update()
        return False
    mesh.clear_geometry()
    mesh.vertices.add(len(verts))
    mesh.loops.add(tris.size)
    mesh.polygons.add(len(tris))
    mesh.vertices.foreach_set("co", verts.ravel())
    mesh.loops.foreach_set("vertex_index", tris.ravel())
    mesh.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    mesh.update()
    return True


def new_mesh_object(name: str, vertices: np.ndarray, faces: np.ndarray,
                    collection: "bpy.types.Collection | None" = None) -> "bpy.types.Object":
    """Create a mesh object from arrays and link it to ``collection`` (default: scene root)."""
    mesh = bpy.data.meshes.new(name)
    set_mesh_arrays(mesh, vertices, faces)
    obj = bpy.data.objects.new(name, mesh)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def box_arrays(length: float, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A box with its origin at the footprint centre on the ground (z = 0 at the bottom).

    Returns:
        vertices (8, 3) in metres and triangles (12, 3).
    """
    x, y = length / 2.0, width / 2.0
    v = np.array([[-x, -y, 0], [x, -y, 0], [x, y, 0], [-x, y, 0],
                  [-x, -y, height], [x, -y, height], [x, y, height], [-x, y, height]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int64)
    return v, f


def get_collection(name: str, parent: "bpy.types.Collection | None" = None) -> "bpy.types.Collection":
    """The collection ``name`` (created and linked under ``parent`` / the scene if missing)."""
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
    parent = parent or bpy.context.scene.collection
    if coll.name not in parent.children:
        parent.children.link(coll)
    return coll


def remove_collection(name: str) -> None:
    """Delete a collection and every object in it (and the orphaned data)."""
    coll = bpy.data.collections.get(name)
    if coll is None:
        return
    for obj in list(coll.all_objects):
        data = obj.data
        bpy.data.objects.remove(obj, do_unlink=True)
        if data is not None and data.users == 0:
            if isinstance(data, bpy.types.Mesh):
                bpy.data.meshes.remove(data)
            elif isinstance(data, bpy.types.Curve):
                bpy.data.curves.remove(data)
    for child in list(coll.children):
        remove_collection(child.name)
    bpy.data.collections.remove(coll)
