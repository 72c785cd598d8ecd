"""Embree ray casting (via ``embreex``, Embree 4) on static triangle meshes.

A :class:`MeshBVH` is one Embree scene built once from a mesh in its own frame. The LiDAR
pipeline keeps one for the static background (coordinates centred, float32) and one per
distinct actor mesh (in the actor's local frame); an actor is hit by expressing the rays in
its frame, so nothing is rebuilt per frame.

``embreex``'s ``EmbreeScene.run`` casts one ray at a time (``rtcIntersect1``) on the calling
thread; only BVH builds use Embree's TBB thread pool. Its ``dists`` argument is both the
per-ray ``tfar`` limit and the output: Embree writes the hit distance into it in place. We use
that to keep the nearest hit over several scenes without copies: cast each scene with the
current nearest distances and only closer hits come back.
"""
from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["MeshBVH", "mesh_key", "cast_nearest"]

_DEVICE = None


def _device():
    """One Embree device for the whole process (a device per scene costs memory and time)."""
    global _DEVICE
    if _DEVICE is None:
        from embreex import rtcore as rtc

        _DEVICE = rtc.EmbreeDevice()
    return _DEVICE


def mesh_key(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Content hash of a mesh (vertices as float32, faces as int32): the BVH cache key."""
    h = hashlib.blake2b(digest_size=16)
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    h.update(np.asarray(v.shape, dtype=np.int64).tobytes())
    h.update(v.tobytes())
    h.update(np.asarray(f.shape, dtype=np.int64).tobytes())
    h.update(f.tobytes())
    return h.hexdigest()


class MeshBVH:
    """An Embree scene over one triangle mesh, in the mesh's own frame.

    Args:
        vertices: (V, 3) vertex positions, metres; cast to float32 (centre large coordinates
            before: the caller's job, see :class:`~adv3d_runner.sensors.world.LidarWorld`).
        faces: (F, 3) vertex indices.

    Attributes:
        n_faces: F (0 means the mesh is empty and every ray misses).
        xy_radius: radius of the smallest origin-centred circle holding the mesh's xy footprint.
        footprint: (xmin, xmax, ymin, ymax) of the vertices, the mesh's axis-aligned xy box.
        radius: radius of the origin-centred sphere holding the mesh.
        z_range: (zmin, zmax) of the vertices.
        face_normals: (F + 1, 3) float32 unit face normals (zero for degenerate faces), with
            a trailing zero row so that a miss (face -1) indexes safely.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        v = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
        f = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(f"faces index outside 0..{len(v) - 1}")
        self.n_faces = int(len(f))
        if len(v):
            v64 = v.astype(np.float64)
            self.xy_radius = float(np.sqrt((v64[:, 0] ** 2 + v64[:, 1] ** 2).max()))
            self.radius = float(np.sqrt((v64 ** 2).sum(axis=1).max()))
            self.z_range = (float(v64[:, 2].min()), float(v64[:, 2].max()))
            self.footprint = (float(v64[:, 0].min()), float(v64[:, 0].max()),
                              float(v64[:, 1].min()), float(v64[:, 1].max()))
        else:
            self.xy_radius = self.radius = 0.0
            self.z_range = (0.0, 0.0)
            self.footprint = (0.0, 0.0, 0.0, 0.0)
        normals = np.zeros((self.n_faces + 1, 3), np.float32)
        if self.n_faces:
            v64 = v.astype(np.float64)
            cross = np.cross(v64[f[:, 1]] - v64[f[:, 0]], v64[f[:, 2]] - v64[f[:, 0]])
            norm = np.linalg.norm(cross, axis=1, keepdims=True)
            normals[:-1] = np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)
        self.face_normals = normals
        # The same as contiguous columns: 1-D gathers are several times faster than row gathers.
        self.normal_columns = tuple(np.ascontiguousarray(normals[:, j]) for j in range(3))
        self._scene = None
        if self.n_faces:
            from embreex import rtcore_scene as rtcs
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcs.EmbreeScene(_device())
            TriangleMesh(self._scene, v, f)
            # Build the BVH now (the first query would otherwise pay for it).
            self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), output=1)

    def intersect(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray):
        """Cast rays; ``tfar`` is updated IN PLACE to the hit distance where a hit is closer.

        Args:
            origins: (N, 3) or (1, 3)-broadcast float32 ray origins in the mesh frame.
            directions: (N, 3) float32 directions (distances are in units of |direction|).
            tfar: (N,) float32 contiguous, the current limit per ray; overwritten on a hit.

        Returns:
            (prim, normal): (N,) int32 face index hit (-1 = no closer hit) and (N, 3) float32
            unnormalised geometric normals (meaningful where prim >= 0).
        """
        n = len(directions)
        if self._scene is None or n == 0:
            return np.full(n, -1, np.int32), np.zeros((n, 3), np.float32)
        if origins.shape[0] != n:
            origins = np.broadcast_to(origins, (n, 3))
        out = self._scene.run(origins, directions, dists=tfar, output=1)
        return out["primID"], out["Ng"]


def cast_nearest(bvh: MeshBVH, origins: np.ndarray, directions: np.ndarray, max_range: float):
    """Nearest hit of each ray on one mesh (convenience for tests and the raw-Embree benchmark).

    Returns:
        (t, prim, normal): (N,) float32 distance (``max_range`` where missed), (N,) int32 face
        index (-1 = miss), (N, 3) float32 normals.
    """
    t = np.full(len(directions), max_range, np.float32)
    prim, normal = bvh.intersect(np.ascontiguousarray(origins, np.float32),
                                 np.ascontiguousarray(directions, np.float32), t)
    return t, prim, normal
