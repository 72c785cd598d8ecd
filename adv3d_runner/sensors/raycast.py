"""Embree 4 ray casting on static triangle meshes.

A :class:`MeshBVH` is one Embree scene built once from a mesh in its own frame. The LiDAR
pipeline keeps one for the static background (coordinates centred, float32) and one per
distinct actor mesh (in the actor's local frame); an actor is hit by expressing the rays in
its frame, so nothing is rebuilt per frame.

Casts go through :mod:`adv3d_runner.sensors.embree`, a direct binding to the Embree library
that ``embreex`` bundles: a compiled loop (numba, cached) fills packets of 8 rays per
``rtcIntersect8`` call on the calling thread, without the GIL. The distances and faces are bit
for bit those of ``embreex``'s ``EmbreeScene.run`` (same library, robust scenes, rays set up the
same way), which casts one ray per ``rtcIntersect1`` from a Cython loop: 13.1 ms of CPU
against 8.8 for a frame's HDL-64E background cast (docs/lidar.md, "Direct Embree binding").
Where the binding is unavailable (:func:`~adv3d_runner.sensors.embree.available` is False:
another wheel layout or platform), ``MeshBVH`` falls back to ``embreex``'s ``run``, with the
same results. Only BVH builds use Embree's TBB thread pool.

``tfar`` is both the per-ray limit and the output: Embree writes the hit distance into it in
place. We use that to keep the nearest hit over several scenes without copies: cast each scene
with the current nearest distances and only closer hits come back.
"""
from __future__ import annotations

import hashlib

import numpy as np

from . import embree
from .coherent import MIN_SIN_INCIDENCE, FaceCertificates, cached_face_certificates, uncertain_rays

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
        direct: cast through the direct binding (:mod:`~adv3d_runner.sensors.embree`, True) or
            ``embreex``'s ``run`` (False); None (default): the binding where it is available.
            Same results either way.
        coherent: cast with Embree's coherent query and certify its hits
            (:mod:`~adv3d_runner.sensors.coherent`): the same results, about half the time on a
            LiDAR frame of rays in neighbouring packets; costs a certificate per face at build
            (about 0.2 s for a 9k-face highway). Only with the direct binding, and not for a
            mesh with too many overlapping face boxes (``coherent.MAX_SWEEP_PAIRS``).

    Attributes:
        n_faces: F (0 means the mesh is empty and every ray misses).
        xy_radius: radius of the smallest origin-centred circle holding the mesh's xy footprint.
        footprint: (xmin, xmax, ymin, ymax) of the vertices, the mesh's axis-aligned xy box.
        radius: radius of the origin-centred sphere holding the mesh.
        z_range: (zmin, zmax) of the vertices.
        direct: whether casts go through the direct binding (False for an empty mesh).
        certificates: the :class:`~adv3d_runner.sensors.coherent.FaceCertificates` of a
            coherent mesh (None: plain casts); ``coherent_rays`` and ``recast_rays`` count its
            rays and those cast again.
        window_shape: (7,) float64 xy_radius, footprint and z_range in one row (what a
            LiDAR's compiled actor windows read, ``kernels.actor_windows``).
        face_normals: (F + 1, 3) float32 unit face normals (zero for degenerate faces), with
            a trailing zero row so that a miss (face -1) indexes safely.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, direct: bool | None = None,
                 coherent: bool = False):
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
        # what a LiDAR's actor windows need of the mesh, in one row (kernels.actor_windows)
        self.window_shape = np.array([self.xy_radius, *self.footprint, *self.z_range], np.float64)
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
        self.direct = False
        self.coherent_rays = self.recast_rays = 0  # counters of the coherent path
        self.certificates: FaceCertificates | None = None  # set: casts are coherent, verified
        if self.n_faces:
            if direct is None:
                direct = embree.available()
            if direct:
                self._scene = embree.TriangleScene(v, f)  # committed: the BVH is built now
                self.direct = True
                if coherent:
                    self.certificates = cached_face_certificates(v, f)
            else:
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
            tfar: (N,) float32, the current limit per ray; overwritten on a hit.

        Returns:
            (prim, None): (N,) int32 face index hit (-1 = no closer hit); the second item is
            kept for callers that unpack two (no caller used Embree's geometric normals, the
            face's unit normal is ``face_normals[prim]``).
        """
        n = len(directions)
        if self._scene is None or n == 0:
            return np.full(n, -1, np.int32), None
        if tfar.dtype != np.float32 or tfar.shape != (n,):
            raise ValueError(f"tfar must be ({n},) float32, got {tfar.shape} {tfar.dtype}")
        origins = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        if len(origins) not in (1, n):
            raise ValueError(f"origins must be (1, 3) or ({n}, 3), got {origins.shape}")
        directions = np.ascontiguousarray(directions, dtype=np.float32)
        if not self.direct:
            if len(origins) != n:
                origins = np.broadcast_to(origins, (n, 3))
            return self._scene.run(origins, directions, dists=tfar, output=1)["primID"], None
        cast = self._scene.intersect if self.certificates is None else self._intersect_coherent
        if tfar.flags.c_contiguous:
            return cast(origins, directions, tfar), None
        t = np.ascontiguousarray(tfar)  # a strided view: cast a copy, write it back
        prim = cast(origins, directions, t)
        tfar[...] = t
        return prim, None

    def _intersect_coherent(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> np.ndarray:
        """The reference hits from a coherent cast plus a reference cast of the rays it cannot
        certify (:mod:`adv3d_runner.sensors.coherent`); arguments as :meth:`intersect`'s."""
        cert = self.certificates
        limit = tfar.copy()
        uv = np.empty((len(directions), 2), np.float32)
        prim = self._scene.intersect(origins, directions, tfar, uv=uv, coherent=True)
        redo = uncertain_rays(prim, tfar, uv, directions, limit, cert.crowded, cert.altitudes, cert.normals,
                              cert.cell_slot, cert.cell_frame, cert.cell_crowded, cert.margin, MIN_SIN_INCIDENCE)
        self.recast_rays += len(redo)
        self.coherent_rays += len(directions)
        if len(redo):
            t = limit[redo]
            o = origins if len(origins) == 1 else np.ascontiguousarray(origins[redo])
            prim[redo] = self._scene.intersect(o, np.ascontiguousarray(directions[redo]), t)
            tfar[redo] = t
        return prim


def cast_nearest(bvh: MeshBVH, origins: np.ndarray, directions: np.ndarray, max_range: float):
    """Nearest hit of each ray on one mesh (convenience for tests and the raw-Embree benchmark).

    Returns:
        (t, prim, normal): (N,) float32 distance (``max_range`` where missed), (N,) int32 face
        index (-1 = miss), (N, 3) float32 unit normal of the face hit (``bvh.face_normals``,
        zero where missed).
    """
    t = np.full(len(directions), max_range, np.float32)
    prim, _ = bvh.intersect(origins, directions, t)
    return t, prim, bvh.face_normals[prim]
