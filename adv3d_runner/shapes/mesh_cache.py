"""Library meshes as plain arrays, read once per content from a user cache instead of parsing
the glb through trimesh in every process (docs/performance.md).

:func:`library_mesh_arrays` returns what :func:`adv3d_runner.shapes.mesh_io.read_library_mesh`
reads (vertices in the convention frame, faces), bit for bit: the first read of a file's
content parses it with trimesh and stores ``vertices`` / ``faces`` / ``bounds`` in
``<cache>/meshes/<key>.npz`` (:func:`adv3d_runner.fileio.user_cache_dir`), where ``key`` is the
SHA-256 of the file's bytes, the reader's version and trimesh's version. Later reads load the
npz without pickle (``allow_pickle=False``) and check its shapes, dtypes, face indices and
bounds; a cache file that fails any check, or cannot be read or written, is ignored and the
glb parsed again (a corrupt cache costs time, never a wrong mesh).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Bumped when :func:`_parse` changes what it stores.
CACHE_VERSION = "mesh-arrays-1"
#: Largest library mesh file hashed and cached (bytes); larger ones are parsed each time.
MAX_FILE_BYTES = 256 << 20


@dataclass
class MeshArrays:
    """A triangle mesh as arrays (the attribute names of ``trimesh.Trimesh`` the simulator uses).

    Attributes:
        vertices: (n, 3) float64, m.
        faces: (m, 3) int64 indices into ``vertices``.
        bounds: (2, 3) float64 [min, max] of the vertices the faces use (``Trimesh.bounds``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    bounds: np.ndarray

    def copy(self) -> "MeshArrays":
        """A deep copy (the arrays copied)."""
        return MeshArrays(self.vertices.copy(), self.faces.copy(), self.bounds.copy())


def _face_bounds(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    used = vertices[np.unique(faces)] if faces.size else vertices[:0]
    if not len(used):
        return np.zeros((2, 3))
    return np.array([used.min(axis=0), used.max(axis=0)])


def _parse(path: Path) -> MeshArrays:
    from .mesh_io import read_library_mesh

    mesh = read_library_mesh(path)
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    bounds = mesh.bounds
    bounds = np.zeros((2, 3)) if bounds is None else np.asarray(bounds, dtype=np.float64)
    return MeshArrays(vertices, faces, bounds)


def _key(data: bytes) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        reader = version("trimesh")
    except PackageNotFoundError:
        reader = "-"
    h = hashlib.sha256(data)
    h.update(f"\0{CACHE_VERSION}\0trimesh {reader}".encode())
    return h.hexdigest()


def cache_path(data: bytes) -> Path:
    """The cache file of a mesh file whose bytes are ``data``."""
    from ..fileio import user_cache_dir

    return user_cache_dir() / "meshes" / f"{_key(data)[:40]}.npz"


def _load(path: Path) -> MeshArrays | None:
    """The arrays of a cache file, or None when it is missing, unreadable or inconsistent."""
    try:
        with np.load(path, allow_pickle=False) as z:
            v, f, b = z["vertices"], z["faces"], z["bounds"]
    except Exception:  # noqa: BLE001 - a corrupt zip or npy raises many types
        return None
    if (v.dtype != np.float64 or v.ndim != 2 or v.shape[1] != 3 or f.dtype != np.int64 or f.ndim != 2
            or f.shape[1] != 3 or b.dtype != np.float64 or b.shape != (2, 3) or not np.isfinite(v).all()):
        return None
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        return None
    if not np.array_equal(_face_bounds(v, f), b):
        return None
    return MeshArrays(v, f, b)


def library_mesh_arrays(path: str | Path) -> MeshArrays:
    """The library mesh file ``path`` as :class:`MeshArrays` (what ``read_library_mesh`` reads),
    from the content-keyed cache when it holds it (see the module docstring).

    Raises:
        MeshImportError: the file is missing or unreadable (as ``read_library_mesh``).
    """
    from ..errors import MeshImportError
    from ..fileio import atomic_path, npz_bytes

    path = Path(path)
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            return _parse(path)
        data = path.read_bytes()
    except FileNotFoundError:
        raise MeshImportError(f"{path}: library mesh file is missing") from None
    except OSError:
        return _parse(path)  # its own error names the file
    target = cache_path(data)
    cached = _load(target) if target.exists() else None
    if cached is not None:
        return cached
    mesh = _parse(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tmp.write_bytes(npz_bytes({"vertices": mesh.vertices, "faces": mesh.faces, "bounds": mesh.bounds}))
    except OSError:
        pass  # a read-only cache: parse again next time
    return mesh
