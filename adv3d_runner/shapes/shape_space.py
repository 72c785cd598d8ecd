"""The PCA shape space over vehicle SDF volumes (paper section 3.2, appendix A.2).

``z = W^T (phi - mu)``, ``G(z) = MarchingCubes(W z + mu)``. A query is a *unit vector*
``u`` in ``[0, 1]^(K+2)``: the first K entries map linearly to ``[z_min, z_max]`` (the latent
range over the library), the last two to the width and length scales in ``[0.8, 1.3]``.

File contract (``assets/shape_space/*.npz``, documented in docs/formats.md): a zip of ``.npy``
arrays written deterministically (fixed member order and timestamps), so building twice gives
byte-identical files. Loaded with ``allow_pickle=False`` and validated field by field.

This module needs only numpy and scikit-image for loading and decoding (the Blender add-on
uses it in-process); building imports libigl through ``sdf``.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import Adv3dError, ConfigError
from ..fileio import REPO_ROOT, atomic_write_bytes, npz_bytes
from ..progress import Steps
from ..validate import check_header, read_npz
from .decode import extract_surface
from .sdf import DEFAULT_METHOD, DEFAULT_TRUNCATION, GridSpec

FORMAT = "adv3d.shape_space"
VERSION = 1
DEFAULT_RESOLUTION = 64
DEFAULT_K = 3
SCALE_RANGE = (0.8, 1.3)
DEFAULT_SHAPE_SPACE: Path = REPO_ROOT / "assets" / "shape_space" / "vehicles_64.npz"

# Relative eigenvalue below which a principal direction counts as absent (duplicated assets,
# fewer assets than K + 1). float32 SDFs have ~1e-7 relative noise, so 1e-10 on variance
# (1e-5 on amplitude) separates real from numerical directions.
_RANK_TOL = 1e-10
_ARRAYS = ("meta", "mean", "components", "latents", "asset_ids")
# Bounds of the contract: a vehicle grid of at most 50 m, width/length scales within [0.1, 10]
# (the shipped range is 0.8-1.3), latents within 1e6: a file outside them is refused on load,
# never decoded into a 5e11 m car.
MAX_EXTENT_M = 50.0
SCALE_LIMITS = (0.1, 10.0)
MAX_LATENT = 1e6


@dataclass
class ShapeSpace:
    """A built shape space.

    Attributes:
        grid: where the SDF samples lie (resolution N, cube edge, ground plane, truncation).
        mean: (N^3,) float32 mean SDF, unit-cube units.
        components: (K, N^3) float32 orthonormal principal directions (zero-variance
            directions pad the rank when the library has fewer than K + 1 distinct shapes).
        explained_variance: (K,) float64 variance along each component (0 for padding).
        explained_variance_ratio: (K,) float64 share of the total variance.
        latents: (M, K) float64 latent of every library asset.
        asset_ids: the M asset ids, in library order.
        latent_min, latent_max: (K,) float64 per-dimension range over ``latents``.
        scale_range: (low, high) of the width/length scales.
        method: SDF method the space was built with.
        rank: number of non-padding components.
        source: where it was loaded from (not stored).
    """

    grid: GridSpec
    mean: np.ndarray
    components: np.ndarray
    explained_variance: np.ndarray
    explained_variance_ratio: np.ndarray
    latents: np.ndarray
    asset_ids: list[str]
    latent_min: np.ndarray
    latent_max: np.ndarray
    scale_range: tuple[float, float] = SCALE_RANGE
    method: str = DEFAULT_METHOD
    rank: int = 0
    build: dict = field(default_factory=dict)
    source: Path | None = None

    # ------------------------------------------------------------------ basic properties
    @property
    def k(self) -> int:
        """Number of latent dimensions K (the unit vector has K + 2 entries)."""
        return int(self.components.shape[0])

    @property
    def dim(self) -> int:
        """Length of a unit vector: K + 2."""
        return self.k + 2

    @property
    def content_hash(self) -> str:
        return _content_hash(self._meta_without_hash(), self._arrays())

    # ------------------------------------------------------------------ unit <-> latent
    def check_unit(self, u: Any) -> np.ndarray:
        """Validate a unit vector: (K+2,) finite, every entry in [0, 1].

        Raises:
            ConfigError: wrong length, NaN/inf, or an entry outside [0, 1].
        """
        try:
            arr = np.asarray(u, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(f"unit vector must be {self.dim} numbers in [0, 1], got {u!r}") from None
        if arr.ndim != 1 or arr.shape[0] != self.dim:
            raise ConfigError(
                f"unit vector must have K + 2 = {self.dim} entries (K={self.k} latents, width and "
                f"length scale), got shape {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            raise ConfigError(f"unit vector has NaN or infinite entries: {arr.tolist()}")
        bad = np.flatnonzero((arr < 0.0) | (arr > 1.0))
        if len(bad):
            raise ConfigError(
                f"unit vector entries must lie in [0, 1]; entry {int(bad[0])} is {arr[bad[0]]!r}"
            )
        return arr

    def unit_to_latent(self, u: Any) -> tuple[np.ndarray, np.ndarray]:
        """Unit vector -> (z (K,) inside [latent_min, latent_max], scales (2,) = (width, length))."""
        arr = self.check_unit(u)
        z = self.latent_min + arr[: self.k] * (self.latent_max - self.latent_min)
        lo, hi = self.scale_range
        scales = lo + arr[self.k :] * (hi - lo)
        return z, scales

    def latent_to_unit(self, z: Any, scales: Sequence[float] = (1.0, 1.0)) -> np.ndarray:
        """Inverse of ``unit_to_latent``. A latent dimension with zero range maps to 0.5.

        Raises:
            ConfigError: wrong shape, non-finite, or outside the latent box / scale range.
        """
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        s = np.asarray(scales, dtype=np.float64).reshape(-1)
        if z.shape != (self.k,) or s.shape != (2,):
            raise ConfigError(f"need z of shape ({self.k},) and 2 scales, got {z.shape} and {s.shape}")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(s))):
            raise ConfigError("latent or scales contain NaN or infinite values")
        span = self.latent_max - self.latent_min
        safe = np.where(span > 0, span, 1.0)
        uz = np.where(span > 0, (z - self.latent_min) / safe, 0.5)
        lo, hi = self.scale_range
        us = (s - lo) / (hi - lo)
        u = np.concatenate([uz, us])
        tol = 1e-9
        if np.any(u < -tol) or np.any(u > 1 + tol):
            raise ConfigError(f"latent/scales lie outside the shape space box (unit vector {u.tolist()})")
        return np.clip(u, 0.0, 1.0)

    def sample_unit(self, rng: np.random.Generator) -> np.ndarray:
        """A uniform random unit vector (K+2,) from ``rng``."""
        return rng.random(self.dim)

    # ------------------------------------------------------------------ decode / encode
    def decode_sdf(self, z: Any) -> np.ndarray:
        """SDF volume ``W z + mu`` as (N, N, N) float32 (no bounds check on ``z``)."""
        z = np.asarray(z, dtype=np.float64).reshape(-1)
        if z.shape != (self.k,) or not np.all(np.isfinite(z)):
            raise ConfigError(f"latent must be {self.k} finite numbers, got {z.tolist()}")
        field_ = self.mean + z.astype(np.float32) @ self.components
        n = self.grid.resolution
        return field_.reshape(n, n, n)

    def decode_latent(self, z: Any, scales: Sequence[float] = (1.0, 1.0),
                      info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mesh arrays of a latent (any finite z, not limited to the library box).

        ``info``, if a dict, receives what the decoder's clean-up dropped (parts, cavities,
        volume: see ``decode.extract_surface``).

        Raises:
            EmptySurfaceError: the field has no zero crossing.
        """
        s = np.asarray(scales, dtype=np.float64).reshape(-1)
        if s.shape != (2,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ConfigError(f"scales must be 2 positive finite numbers, got {s.tolist()}")
        return extract_surface(self.decode_sdf(z), self.grid, (float(s[0]), float(s[1])), info=info)

    def decode_arrays(self, u: Any, info: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Unit vector -> (vertices (V, 3) float64 metres, faces (F, 3) int64); the fast path.

        The mesh is closed, wound counter-clockwise from outside, origin at the centre of the
        body's footprint (its largest closed part) with its lowest point at z = 0, +x forward.
        ``info``: see :meth:`decode_latent`.

        Raises:
            ConfigError: bad unit vector. EmptySurfaceError: no surface (invalid query).
        """
        z, scales = self.unit_to_latent(u)
        return self.decode_latent(z, scales, info=info)

    def decode(self, u: Any):
        """Unit vector -> ``trimesh.Trimesh`` (metric, watertight, outward normals)."""
        import trimesh

        v, f = self.decode_arrays(u)
        return trimesh.Trimesh(vertices=v, faces=f, process=False)

    def encode(self, sdf: np.ndarray) -> np.ndarray:
        """Project an SDF volume (N, N, N) or (N^3,) on the components: (K,) float64."""
        x = np.asarray(sdf, dtype=np.float64).reshape(-1)
        if x.shape != self.mean.shape:
            raise ConfigError(f"SDF must have {self.mean.size} samples, got {x.size}")
        return self.components.astype(np.float64) @ (x - self.mean.astype(np.float64))

    def asset_unit(self, asset_id: str, scales: Sequence[float] = (1.0, 1.0)) -> np.ndarray:
        """Unit vector of a library asset (its latent, scales 1 by default)."""
        try:
            i = self.asset_ids.index(asset_id)
        except ValueError:
            raise ConfigError(f"asset {asset_id!r} is not in this shape space") from None
        return self.latent_to_unit(self.latents[i], scales)

    def nearest_asset(self, u: Any) -> str:
        """Id of the library asset whose latent is closest to the latent of ``u``."""
        z, _ = self.unit_to_latent(u)
        d = np.linalg.norm(self.latents - z[None, :], axis=1)
        return self.asset_ids[int(np.argmin(d))]

    # ------------------------------------------------------------------ persistence
    def _meta_without_hash(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "grid": self.grid.as_dict(),
            "k": self.k,
            "rank": int(self.rank),
            "method": self.method,
            "scale_range": [float(self.scale_range[0]), float(self.scale_range[1])],
            "explained_variance": [float(x) for x in self.explained_variance],
            "explained_variance_ratio": [float(x) for x in self.explained_variance_ratio],
            "latent_min": [float(x) for x in self.latent_min],
            "latent_max": [float(x) for x in self.latent_max],
            "build": self.build,
        }

    def _arrays(self) -> dict[str, np.ndarray]:
        return {
            "mean": np.ascontiguousarray(self.mean, dtype=np.float32),
            "components": np.ascontiguousarray(self.components, dtype=np.float32),
            "latents": np.ascontiguousarray(self.latents, dtype=np.float64),
            "asset_ids": np.asarray(self.asset_ids, dtype=f"<U{max([1] + [len(a) for a in self.asset_ids])}"),
        }

    def to_bytes(self) -> bytes:
        """The exact bytes of the ``.npz`` file (deterministic)."""
        meta = self._meta_without_hash()
        arrays = self._arrays()
        meta["content_hash"] = _content_hash(meta, arrays)
        members = {"meta": np.asarray(json.dumps(meta, indent=1, allow_nan=False)), **arrays}
        return npz_bytes({name: members[name] for name in _ARRAYS})

    def save(self, path: str | Path) -> Path:
        """Write the ``.npz`` atomically; returns the path."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes())
        return path

    @classmethod
    def load(cls, path: str | Path = DEFAULT_SHAPE_SPACE) -> "ShapeSpace":
        """Load and validate a shape-space file.

        Raises:
            FileFormatError: missing/corrupt file or any field not matching the contract.
        """
        return _load(Path(path))


# ----------------------------------------------------------------------------- file loading


def _content_hash(meta: dict, arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({k: v for k, v in meta.items() if k != "content_hash"}, sort_keys=True).encode())
    for name in ("mean", "components", "latents", "asset_ids"):
        a = arrays[name]
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return "sha256:" + h.hexdigest()


def _load(path: Path) -> ShapeSpace:
    z = read_npz(path, "shape-space .npz file", " (build one with `adv3d shapes build`)")
    z.require(_ARRAYS)
    meta = z.json("meta")
    meta.object("a JSON object")
    check_header(meta, FORMAT, (VERSION,))
    g = meta["grid"]
    g.object("an object with resolution, extent_m, ground_z, truncation")
    res = g["resolution"].integer(lo=8, hi=512)
    extent = g["extent_m"].number(lo=0.0, lo_open=True, hi=MAX_EXTENT_M)
    grid = GridSpec(res, extent, g["ground_z"].number(lo=-extent, hi=extent),
                    g["truncation"].number(lo=0.0, lo_open=True, hi=1.0))
    k = meta["k"].integer(lo=1)
    rank = meta["rank"].integer(lo=0, hi=k)
    d = res**3
    ev = meta["explained_variance"].numbers(length=k, lo=0.0)
    evr = meta["explained_variance_ratio"].numbers(length=k, lo=0.0, hi=1.0)
    zmin = meta["latent_min"].numbers(length=k, lo=-MAX_LATENT, hi=MAX_LATENT)
    zmax = meta["latent_max"].numbers(length=k, lo=-MAX_LATENT, hi=MAX_LATENT)
    if np.any(zmin > zmax):
        meta["latent_max"].fail("latent_max >= latent_min in every dimension", zmax.tolist())
    sr = meta["scale_range"].numbers(length=2, lo=SCALE_LIMITS[0], hi=SCALE_LIMITS[1])
    if not sr[0] < sr[1]:
        meta["scale_range"].fail(f"low < high, both in [{SCALE_LIMITS[0]:g}, {SCALE_LIMITS[1]:g}]", sr.tolist())
    method = meta["method"].string(empty=True)
    build = meta.get("build", {}).object()
    mean = z.array("mean", dtype=np.float32, shape=(d,), finite=True)
    comps = z.array("components", dtype=np.float32, shape=(k, d), finite=True)
    ids_arr = z.array("asset_ids", kind="U", ndim=1)
    if len(ids_arr) == 0:
        z.fail("asset_ids", "a non-empty 1-d unicode array", f"{ids_arr.dtype} {ids_arr.shape}")
    latents = z.array("latents", dtype=np.float64, shape=(len(ids_arr), k), finite=True)
    space = ShapeSpace(
        grid=grid, mean=np.ascontiguousarray(mean), components=np.ascontiguousarray(comps),
        explained_variance=ev, explained_variance_ratio=evr, latents=latents,
        asset_ids=[str(x) for x in ids_arr], latent_min=zmin, latent_max=zmax,
        scale_range=(float(sr[0]), float(sr[1])), method=method, rank=rank, build=build, source=path,
    )
    stored = meta.get("content_hash").value
    if stored != space.content_hash:
        meta.child("content_hash").fail(f"{space.content_hash} (the hash of the stored data)", stored)
    return space


# ----------------------------------------------------------------------------- building


def fit_pca(data: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """PCA of M flattened SDFs through the small M x M Gram matrix.

    Args:
        data: (M, D) samples (any float dtype).
        k: number of components wanted.
    Returns:
        mean (D,) float64, components (k, D) float64 orthonormal, explained variance (k,),
        explained variance ratio (k,), rank (components with non-zero variance; the rest pad
        with deterministic zero-variance directions orthogonal to the others).
    Component signs are fixed so the largest-magnitude entry of each is positive.
    """
    if k < 1:
        raise ConfigError(f"K must be >= 1, got {k}")
    x = np.asarray(data, dtype=np.float64)
    m, d = x.shape
    if m == 0:
        raise ConfigError("cannot build a shape space from zero assets")
    if k > d:
        raise ConfigError(f"K={k} exceeds the number of SDF samples {d}")
    mean = x.mean(axis=0)
    xc = x - mean
    # kept: eigh of the M x M Gram matrix, not np.linalg.svd / scikit-learn (same directions to
    # 1e-15, but other last bits: at 24^3, 51 of 41472 float32 component entries and every
    # variance differ, which would change the shipped shape-space bytes)
    gram = xc @ xc.T
    evals, evecs = np.linalg.eigh(gram)
    order = np.argsort(-evals, kind="stable")
    evals, evecs = evals[order], evecs[:, order]
    top = float(evals[0]) if m else 0.0
    rank = int(np.sum(evals > max(top, 0.0) * _RANK_TOL)) if top > 0 else 0
    rank = min(rank, k, m - 1)
    comps = np.zeros((k, d), dtype=np.float64)
    for i in range(rank):
        c = xc.T @ evecs[:, i]
        comps[i] = c / np.linalg.norm(c)
    # Re-orthonormalise (tiny eigenvalues give slightly non-orthogonal directions).
    if rank:
        q, _ = np.linalg.qr(comps[:rank].T)
        comps[:rank] = q.T * np.sign(np.einsum("ij,ij->i", q.T, comps[:rank]))[:, None]
    # Pad: coordinate directions, orthogonalised against what is there (deterministic).
    j = 0
    for i in range(rank, k):
        while True:
            e = np.zeros(d)
            e[j] = 1.0
            j += 1
            e -= comps[:i].T @ (comps[:i] @ e)
            n = np.linalg.norm(e)
            if n > 0.5:
                comps[i] = e / n
                break
    # Deterministic sign: the largest-|.| entry of each component is positive.
    idx = np.argmax(np.abs(comps), axis=1)
    comps *= np.sign(comps[np.arange(k), idx])[:, None]
    var = np.zeros(k)
    var[:rank] = np.maximum(evals[:rank], 0.0) / max(m - 1, 1)
    total = float(np.maximum(evals, 0.0).sum()) / max(m - 1, 1)
    ratio = var / total if total > 0 else np.zeros(k)
    return mean, comps, var, ratio, rank


def shape_space_from_sdfs(
    sdfs: np.ndarray,
    asset_ids: Sequence[str],
    grid: GridSpec,
    k: int = DEFAULT_K,
    method: str = DEFAULT_METHOD,
    build: dict | None = None,
) -> ShapeSpace:
    """Fit the PCA space to (M, N, N, N) SDF volumes of the named assets."""
    sdfs = np.asarray(sdfs)
    m = len(asset_ids)
    if sdfs.shape[0] != m or sdfs[0].size != grid.resolution**3:
        raise ConfigError(f"need {m} SDF volumes of {grid.resolution}^3 samples, got {sdfs.shape}")
    if len(set(asset_ids)) != m:
        raise ConfigError("asset ids must be unique")
    flat = sdfs.reshape(m, -1).astype(np.float32)
    mean, comps, var, ratio, rank = fit_pca(flat, k)
    mean32 = mean.astype(np.float32)
    comps32 = comps.astype(np.float32)
    space = ShapeSpace(
        grid=grid, mean=mean32, components=comps32, explained_variance=var, explained_variance_ratio=ratio,
        latents=np.zeros((m, k)), asset_ids=list(asset_ids), latent_min=np.zeros(k), latent_max=np.zeros(k),
        method=method, rank=rank, build=dict(build or {}),
    )
    # Latents with the stored float32 arrays, exactly as ``encode`` computes them.
    lat = np.stack([space.encode(flat[i]) for i in range(m)])
    lat[:, rank:] = 0.0  # padding directions carry no library variation
    space.latents = lat
    space.latent_min = lat.min(axis=0)
    space.latent_max = lat.max(axis=0)
    return space


def library_fingerprint(assets: Sequence, meshes: Sequence) -> str:
    """SHA-256 over the ids, recorded dimensions and mesh geometry of the shape-space assets.

    Stored in the built file (``build.library_fingerprint``) so a stale shape space (library
    changed since the build) can be detected without rebuilding.
    """
    h = hashlib.sha256()
    for a, mesh in zip(assets, meshes):
        h.update(a.id.encode() + b"\0")
        h.update(np.asarray(a.dimensions, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return "sha256:" + h.hexdigest()


def library_sdfs(
    library,
    resolution: int = DEFAULT_RESOLUTION,
    method: str = DEFAULT_METHOD,
    truncation: float = DEFAULT_TRUNCATION,
    progress: bool = True,
    mesh_loader: Callable | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> tuple[GridSpec, list, np.ndarray]:
    """SDF volumes of every shape-space asset on the common grid.

    ``progress`` shows a terminal bar; ``on_progress(done, total)``, when given, is called
    instead before each asset and once at the end.

    Returns:
        grid, the assets (``library.shape_space_assets()`` order), sdfs (M, N, N, N) float32,
        and the ``library_fingerprint`` of the assets.
    """
    from ..progress import run_steps

    steps = library_sdfs_steps(library, resolution, method, truncation, mesh_loader)
    if on_progress is None:
        if not progress:
            return run_steps(steps)
        from ..progress import progress as bar

        ticks = iter(bar(range(len(list(library.shape_space_assets()))), desc=f"SDF {resolution}^3 ({method})",
                         unit="asset"))
        on_progress = lambda done, total: next(ticks, None)  # noqa: E731  (one tick per asset)
    started = -1
    while True:
        try:
            step = next(steps)
        except StopIteration as stop:
            total = len(stop.value[1])
            on_progress(total, total)
            return stop.value
        if step[2] != started:  # (fraction, message, assets_done, assets_total): a new asset
            started = step[2]
            on_progress(step[2], step[3])


def library_sdfs_steps(
    library,
    resolution: int = DEFAULT_RESOLUTION,
    method: str = DEFAULT_METHOD,
    truncation: float = DEFAULT_TRUNCATION,
    mesh_loader: Callable | None = None,
) -> Steps[tuple[GridSpec, list, np.ndarray, str]]:
    """:func:`library_sdfs` as a steps generator (``progress.run_steps``), for callers that must
    stay responsive (the Blender add-on's Build): every step is a short piece of work, yielded
    as ``(fraction, message, assets_done, assets_total)``; returns what ``library_sdfs`` does,
    the same bytes."""
    from ..progress import relay
    from .sdf import grid_for_dimensions, sdf_volume_steps

    if mesh_loader is None:
        from .library import load_asset_mesh as mesh_loader
    assets = list(library.shape_space_assets())
    if not assets:
        raise ConfigError("the vehicle library has no assets marked in_shape_space")
    m = len(assets)
    meshes = []
    for i, a in enumerate(assets):
        meshes.append(mesh_loader(library, a.id))
        yield 0.0, f"reading {a.id}", 0, m
    # Common scale: the larger of the recorded dimensions and the mesh's own extent, so every
    # mesh fits the cube even where the manifest rounds.
    dims = []
    for a, mesh in zip(assets, meshes):
        v = np.asarray(mesh.vertices, dtype=np.float64)
        ext = np.array([2 * np.abs(v[:, 0]).max(), 2 * np.abs(v[:, 1]).max(), v[:, 2].max()])
        dims.append(np.maximum(np.asarray(a.dimensions, dtype=np.float64), ext))
    grid = grid_for_dimensions(dims, resolution, truncation)
    sdfs = np.empty((m, resolution, resolution, resolution), dtype=np.float32)
    for i, (a, mesh) in enumerate(zip(assets, meshes)):
        message = f"SDF {resolution}^3 of {a.id} ({i + 1}/{m})"
        yield i / m, message, i, m
        try:
            sdfs[i] = yield from relay(sdf_volume_steps(mesh.vertices, mesh.faces, grid, method), (i / m, message, i, m))
        except Adv3dError as exc:
            raise Adv3dError(f"asset {a.id}: {exc}") from None
    return grid, assets, sdfs, library_fingerprint(assets, meshes)


def build_shape_space(
    library,
    resolution: int = DEFAULT_RESOLUTION,
    k: int = DEFAULT_K,
    method: str = DEFAULT_METHOD,
    truncation: float = DEFAULT_TRUNCATION,
    progress: bool = True,
    mesh_loader: Callable | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> ShapeSpace:
    """Build the shape space over ``library.shape_space_assets()``.

    Args:
        library: a ``VehicleLibrary``.
        resolution: N of the N^3 SDF grid.
        k: number of principal components.
        method: SDF method (``sdf.METHODS``).
        truncation: SDF clamp, unit-cube units.
        progress: show a progress bar per asset.
        mesh_loader: ``(library, asset_id) -> trimesh.Trimesh``; default ``load_asset_mesh``.
        on_progress: ``(done, total)`` called per asset instead of the terminal bar.
    """
    grid, assets, sdfs, fingerprint = library_sdfs(library, resolution, method, truncation, progress, mesh_loader,
                                                   on_progress)
    return _space_of(grid, assets, sdfs, fingerprint, k, method)


def build_shape_space_steps(
    library,
    resolution: int = DEFAULT_RESOLUTION,
    k: int = DEFAULT_K,
    method: str = DEFAULT_METHOD,
    truncation: float = DEFAULT_TRUNCATION,
    mesh_loader: Callable | None = None,
) -> Steps[ShapeSpace]:
    """:func:`build_shape_space` as a steps generator (``progress.run_steps``): yields
    ``(fraction, message, assets_done, assets_total)`` between short pieces of work (the
    Blender add-on's modal Build); returns the same shape space, byte for byte."""
    grid, assets, sdfs, fingerprint = yield from library_sdfs_steps(library, resolution, method, truncation,
                                                                    mesh_loader)
    yield 1.0, "principal components", len(assets), len(assets)
    return _space_of(grid, assets, sdfs, fingerprint, k, method)


def _space_of(grid: GridSpec, assets: list, sdfs: np.ndarray, fingerprint: str, k: int, method: str) -> ShapeSpace:
    build = {"assets": len(assets), "classes": sorted({a.vehicle_class for a in assets}),
             "library_fingerprint": fingerprint}
    return shape_space_from_sdfs(sdfs, [a.id for a in assets], grid, k, method, build)
