"""How realistic a decoded vehicle shape is (docs/realism.md): the paper's JSD and six other measures.

Every measure is a flat function on arrays; ``realism_report`` gathers them for one shape of
the shape space as a plain JSON-able dict (what an attack journal carries). Definitions,
choices and the figures of the library itself are in docs/realism.md.

Measures
--------
``jsd``
    The paper's realism score (appendix, "Realism Evaluation for Generated Shapes"): 1000
    points sampled uniformly on the shape's surface, their bird's-eye-view 2-D histogram at
    100 x 100, against the histogram of all CAD models of the asset set (the library's
    shape-space vehicles). The value is what the cited code (LiDARGen, Zyrianov et al. 2022,
    ``metrics/histogram/jsd.py``) reports as JSD: ``scipy.spatial.distance.jensenshannon`` of
    the two normalised histograms, i.e. the square root of the Jensen-Shannon divergence in
    nats, in [0, sqrt(ln 2) = 0.833]. Normalisation: metric, not unit size (see ``bev_histogram``).
nearest library vehicle
    Symmetric Chamfer distance in metres (mean of the two directed mean nearest-neighbour
    distances) between the shape's surface sample and each library CAD model's; the nearest
    model and its distance. Also the Euclidean latent distance to the nearest library latent.
latent Mahalanobis distance
    Of the latent ``z`` against the library latents, with a shrunk covariance.
artefacts
    Closed parts of the raw marching-cubes surface (before the decoder's clean-up), floating
    parts and the share of volume the clean-up drops; the genus of the cleaned closed surface
    (Euler characteristic) and a noise-robust genus; the thinnest wall (inward ray thickness).
dimensions
    Bounding-box (L, W, H) against real ranges per vehicle class (``DIMENSION_RANGES``, cited).

"Realistic" limits: JSD, Chamfer and Mahalanobis are compared with the library's own
leave-one-out maximum (stored in the reference file), the artefact measures with fixed rules
tied to the grid (``FLOATING_VOLUME_TOL``, robust genus 0, ``thinnest_wall_m`` >= one voxel),
the dimensions with the cited table.

Reference file (``assets/shape_space/realism_reference.npz``, rebuilt by
``adv3d shapes realism-reference``): the reference histogram, the per-model Chamfer samples
and the leave-one-out figures, written deterministically (fixed member order and zip
timestamps; no pickle) and tied to the shape space by its content hash.

This module needs numpy and scikit-image only (scipy speeds up nearest neighbours and
labelling when present), like decoding, so the Blender add-on can call it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError
from ..fileio import REPO_ROOT, atomic_write_bytes, npz_bytes
from ..validate import check_header, read_npz
from ..vehicle_classes import DIMENSION_RANGES
from .cleaning import connected_vertex_parts
from .decode import MIN_PART_FRACTION, extract_surface
from .sdf import GridSpec

# ----------------------------------------------------------------------------- constants

#: Points sampled on a shape's surface for the JSD (the paper: 1000).
N_POINTS = 1000
#: Bins per axis of the bird's-eye-view histogram (the paper: 100 x 100).
BEV_BINS = 100
#: Edge of the square BEV window in metres, centred on the footprint centre. Decoded shapes
#: never exceed 1.3 x the 6.05 m grid cube = 7.9 m, so 8 m covers every shape the space can
#: produce; bins are 8 cm.
BEV_WINDOW_M = 8.0
#: Surface points per CAD model in the reference histogram. Each model weighs the same; 10x the
#: query's sample so the reference is smooth and the JSD noise comes from the query alone.
REFERENCE_POINTS_PER_MODEL = 10_000
#: Points per model kept for the Chamfer distance (the first ones of the reference sample).
CHAMFER_POINTS = 1000
#: Seed of the reference samples (model i draws from ``default_rng([REFERENCE_SEED, i])``).
REFERENCE_SEED = 20231
#: Shrinkage of the latent covariance toward (trace / K) * I: keeps it invertible with K=3
#: latents over ~18 assets or rank-deficient spaces, and tempers sampling noise.
COVARIANCE_SHRINKAGE = 0.1
#: Floating parts (closed parts other than the largest, before clean-up) holding more than
#: this share of the volume count as an artefact. PCA crumbs hold ~0.03 %; a visible loose
#: piece (a 0.3 m cube beside a car) holds ~0.3 %.
FLOATING_VOLUME_TOL = 1e-3
#: Level offset, in voxels, of the two extra surfaces the robust genus looks at: a tunnel or a
#: handle thinner than this appears at one level only (marching-cubes pinches at grid scale).
GENUS_OFFSET_VOXELS = 0.5
#: Wall thickness statistic: the percentile of the inward-ray thickness over surface samples
#: ("the thinnest wall covering at least 2 % of the surface"); the minimum itself is set by
#: grazing rays at sharp edges and is always about one ray step.
WALL_PERCENTILE = 2.0
#: Surface samples for the wall thickness, ray step and longest ray (metres). Walls thicker
#: than the longest ray are reported at that length (only thin walls matter here).
WALL_SAMPLES = 1000
WALL_STEP_M = 0.02
WALL_MAX_M = 1.5
#: Body dimensions (``body_dimensions``): extents measured on profiles sliced every
#: ``BODY_SLICE_M`` and opened (running minimum then maximum) over ``BODY_WINDOW_M``, so parts
#: shorter than the window along the sweep axis (door mirrors, antennas: 0.1-0.3 m) do not count;
#: ``BODY_SAMPLE_POINTS`` surface points (plus the vertices) make the profiles.
BODY_WINDOW_M = 0.4
BODY_SLICE_M = 0.025
BODY_SAMPLE_POINTS = 20_000
#: ``mesh_realism_report``: open patches seen from outside along less than this share of their
#: rays leave the SDF's sign (``sdf.orient_patches_by_visibility``): the inner skin of a
#: double-walled body seen through its window openings, which otherwise makes the car a hollow
#: shell (docs/realism.md, "Calibration"). An outer panel escapes along most of its rays.
MESH_MIN_VISIBILITY = 0.2


@dataclass(frozen=True)
class RealismLimits:
    """Every check's limit, in one place (docs/realism.md, "Calibration").

    A check passes when the figure is at most (``*_max``) or at least (``*_min``) its limit.
    ``None`` for ``jsd_max``, ``nearest_chamfer_max_m`` and ``mahalanobis_max`` means the
    reference's leave-one-out maximum (the library's own extreme); ``None`` for
    ``thinnest_wall_min_m`` means one voxel of the grid. ``bench/realism_calibration.py`` measures
    the pass rates of real and unrealistic vehicles under these values.

    Attributes:
        jsd_max: BEV Jensen-Shannon distance to the asset set's histogram.
        nearest_chamfer_max_m: Chamfer distance to the nearest CAD model, metres.
        mahalanobis_max: latent Mahalanobis distance.
        floating_volume_max: volume share of closed parts other than the body.
        genus_robust_max: robust genus.
        thinnest_wall_min_m: 2nd-percentile wall thickness, metres.
        dimension_excess_max: relative excess of the body dimensions over the class's range.
    """

    jsd_max: float | None = None
    nearest_chamfer_max_m: float | None = None
    mahalanobis_max: float | None = None
    floating_volume_max: float = FLOATING_VOLUME_TOL
    genus_robust_max: int = 0
    thinnest_wall_min_m: float | None = None
    dimension_excess_max: float = 0.0

    def resolve(self, reference: "RealismReference", voxel_m: float) -> dict:
        """The limits as numbers, keyed by the report's figure names (``report["limits"]``)."""
        return {
            "jsd": float(self.jsd_max if self.jsd_max is not None else reference.jsd_limit),
            "nearest_chamfer_m": float(self.nearest_chamfer_max_m if self.nearest_chamfer_max_m is not None
                                       else reference.chamfer_limit_m),
            "mahalanobis": float(self.mahalanobis_max if self.mahalanobis_max is not None
                                 else reference.mahalanobis_limit),
            "floating_volume_fraction": float(self.floating_volume_max),
            "genus_robust": int(self.genus_robust_max),
            "thinnest_wall_m": float(self.thinnest_wall_min_m if self.thinnest_wall_min_m is not None else voxel_m),
            "dimension_excess": float(self.dimension_excess_max),
        }


#: The limits every report uses unless given others, calibrated on real and unrealistic vehicles
#: (``bench/realism_calibration.py``, docs/realism.md "Calibration"): the JSD at the largest real
#: vehicle's (a lifted pickup, 0.605; the library's leave-one-out maximum is 0.603); robust genus
#: up to 2 (race cars' rear wings on posts are real handles); the wall check at 2 cm, one ray
#: step (wings, spoilers and mirrors decode as sheets thinner than a voxel: the check no longer
#: separates anything and stays as a figure). The floating-volume limit is not relaxed: the
#: hollow double-walled bodies that failed it were fixed in the SDF (``MESH_MIN_VISIBILITY``).
LIMITS = RealismLimits(jsd_max=0.605, genus_robust_max=2, thinnest_wall_min_m=0.02)

#: Checks by figure: ``True`` passes when the figure is at most the limit, ``False`` at least.
_AT_MOST = {"jsd": True, "nearest_chamfer_m": True, "mahalanobis": True, "floating_volume_fraction": True,
            "genus_robust": True, "thinnest_wall_m": False, "dimension_excess": True}


def check_flags(report: dict, limits: dict) -> list[str]:
    """Names of the failed checks among the figures ``report`` has (in ``_AT_MOST`` order).

    ``dimension_excess`` is checked on its largest entry; a figure that is absent or None
    (no latent, no class) is not checked.
    """
    flags = []
    for key, at_most in _AT_MOST.items():
        val = report.get(key)
        if val is None or key not in limits:
            continue
        if key == "dimension_excess":
            val = max(val)
        ok = val <= limits[key] if at_most else val >= limits[key]
        if not ok:
            flags.append(key)
    return flags

DEFAULT_REFERENCE: Path = REPO_ROOT / "assets" / "shape_space" / "realism_reference.npz"
REFERENCE_FORMAT = "adv3d.realism_reference"
REFERENCE_VERSION = 1
_MEMBERS = ("meta", "histogram", "points", "asset_ids")

# ----------------------------------------------------------------------------- real dimensions

# DIMENSION_RANGES (cited real ranges per class) lives with the class list in vehicle_classes.


# ----------------------------------------------------------------------------- sampling, JSD


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int = N_POINTS, seed: Any = 0) -> np.ndarray:
    """Points uniformly distributed over a triangle mesh's surface (area-weighted), seeded.

    Args:
        vertices: (V, 3) float, metres.
        faces: (F, 3) int.
        n: number of points.
        seed: anything ``numpy.random.default_rng`` takes; the same seed, mesh and ``n`` give
            the same points.
    Returns:
        (n, 3) float64 points, metres.
    Raises:
        ConfigError: the mesh has no area.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cum = np.cumsum(area)
    if len(cum) == 0 or not cum[-1] > 0:
        raise ConfigError("cannot sample the surface of a mesh with zero area")
    rng = np.random.default_rng(seed)
    pick = np.minimum(np.searchsorted(cum, rng.random(n) * cum[-1], side="right"), len(cum) - 1)
    r = rng.random((n, 2))
    s = np.sqrt(r[:, 0])  # uniform in the triangle (Osada et al. 2002)
    w = np.stack([1.0 - s, s * (1.0 - r[:, 1]), s * r[:, 1]], axis=1)
    return np.einsum("nk,nkd->nd", w, tri[pick])


def footprint_centred(points: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """Points shifted so the x/y bounding-box centre of ``vertices`` (default: the points) is 0.

    Decoded and library meshes already have their footprint centre at the origin (the vehicle
    convention), so this is a no-op for them; it makes the BEV histogram independent of where
    an arbitrary mesh was modelled.
    """
    p = np.array(points, dtype=np.float64)
    ref = p if vertices is None else np.asarray(vertices, dtype=np.float64)
    p[:, :2] -= 0.5 * (ref[:, :2].min(axis=0) + ref[:, :2].max(axis=0))
    return p


def bev_histogram(points: np.ndarray, bins: int = BEV_BINS, window_m: float = BEV_WINDOW_M) -> np.ndarray:
    """Bird's-eye-view 2-D histogram of points in the vehicle frame.

    Normalisation (why metric): the window is a fixed square of ``window_m`` metres centred on
    the footprint centre, +x (length) along the first axis, and shapes keep their metric size.
    Size is what separates a 3.0 x 1.3 m blob or a 7.4 m flatbed from a sedan, and it is what the
    attack exploits; scaled to unit size, all three would fill the same bins. Points outside the
    window count in the nearest border bin, so no mass is dropped (none of the shape space's
    shapes reach the border).

    Args:
        points: (n, 3) or (n, 2) metres.
        bins: bins per axis.
        window_m: window edge in metres.
    Returns:
        (bins, bins) int64 counts; ``[i, j]`` counts x in bin i and y in bin j.
    """
    p = np.asarray(points, dtype=np.float64)
    width = window_m / bins
    ij = np.floor((p[:, :2] + 0.5 * window_m) / width).astype(np.int64)
    np.clip(ij, 0, bins - 1, out=ij)
    return np.bincount(ij[:, 0] * bins + ij[:, 1], minlength=bins * bins).reshape(bins, bins)


def jsd(p: np.ndarray, q: np.ndarray) -> float:
    """Jensen-Shannon distance of two histograms, as the paper's cited code computes "JSD".

    Both are normalised to sum 1; ``sqrt((KL(p || m) + KL(q || m)) / 2)`` with ``m = (p + q) / 2``
    and natural logarithms: the value of ``scipy.spatial.distance.jensenshannon(p, q)``, which
    LiDARGen's ``jsd_2d`` returns. 0 for equal histograms, sqrt(ln 2) = 0.833 for disjoint ones.
    The divergence itself (nats) is the square of this value.

    Args:
        p, q: histograms of the same shape, non-negative, each with a positive sum.
    """
    a = np.asarray(p, dtype=np.float64).ravel()
    b = np.asarray(q, dtype=np.float64).ravel()
    if a.shape != b.shape or a.sum() <= 0 or b.sum() <= 0 or (a < 0).any() or (b < 0).any():
        raise ConfigError("jsd needs two non-negative histograms of the same shape with positive sums")
    a = a / a.sum()
    b = b / b.sum()
    m = 0.5 * (a + b)
    div = 0.5 * (_kl_terms(a, m) + _kl_terms(b, m))
    return float(np.sqrt(max(div, 0.0)))


def _kl_terms(a: np.ndarray, m: np.ndarray) -> float:
    nz = a > 0  # where a > 0, m >= a / 2 > 0
    return float(np.sum(a[nz] * np.log(a[nz] / m[nz])))


# ----------------------------------------------------------------------------- nearest vehicle


def _kdtree(points: np.ndarray):
    """A scipy ``cKDTree`` of the points, or None without scipy (Blender)."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        return None
    return cKDTree(points)


def _nearest_module():
    """:mod:`.nearest` (the compiled Chamfer sweep), or None without numba (Blender)."""
    try:
        from . import nearest
    except ImportError:
        return None
    return nearest


def _nn_distances(a: np.ndarray, b: np.ndarray, tree_b=None) -> np.ndarray:
    """(len(a),) distance from each point of ``a`` to its nearest point of ``b``, metres.

    ``tree_b``: a prebuilt ``_kdtree(b)``; without scipy, ``_nn_distances_numpy``.
    """
    tree_b = tree_b if tree_b is not None else _kdtree(b)
    if tree_b is None:
        return _nn_distances_numpy(a, b)
    return tree_b.query(a)[0]


def _nn_distances_numpy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """numpy-only ``_nn_distances`` (Blender): brute force in blocks, ~30 ms for 1000 x 1000."""
    out = np.empty(len(a))
    bb = (b * b).sum(axis=1)
    for s in range(0, len(a), 256):
        blk = a[s:s + 256]
        d2 = (blk * blk).sum(axis=1)[:, None] + bb[None, :] - 2.0 * blk @ b.T
        out[s:s + 256] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


def chamfer_distance(a: np.ndarray, b: np.ndarray, tree_a=None, tree_b=None) -> float:
    """Symmetric Chamfer distance between two point samples, metres.

    ``(mean_a min_b |a - b| + mean_b min_a |a - b|) / 2`` (not squared, so it reads as a mean
    surface gap).

    Args:
        a: (n, 3) points. b: (m, 3) points.
        tree_a, tree_b: optional prebuilt ``_kdtree`` of ``a`` / ``b`` (reused across calls).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(0.5 * (_nn_distances(a, b, tree_b).mean() + _nn_distances(b, a, tree_a).mean()))


def regularised_covariance(latents: np.ndarray, shrinkage: float = COVARIANCE_SHRINKAGE) -> np.ndarray:
    """Shrunk sample covariance ``(1 - a) S + a (tr S / K) I`` of (M, K) latents; (K, K)."""
    x = np.asarray(latents, dtype=np.float64)
    k = x.shape[1]
    s = np.cov(x, rowvar=False, ddof=1).reshape(k, k) if len(x) > 1 else np.zeros((k, k))
    scale = np.trace(s) / k if np.trace(s) > 0 else 1.0
    return (1.0 - shrinkage) * s + shrinkage * scale * np.eye(k)


def latent_mahalanobis(z: np.ndarray, latents: np.ndarray, shrinkage: float = COVARIANCE_SHRINKAGE) -> float:
    """Mahalanobis distance of a latent against the library's latents (unitless, in std devs).

    Args:
        z: (K,) latent.
        latents: (M, K) latents of the library assets.
        shrinkage: see ``regularised_covariance``.
    """
    x = np.asarray(latents, dtype=np.float64)
    d = np.asarray(z, dtype=np.float64).reshape(-1) - x.mean(axis=0)
    cov = regularised_covariance(x, shrinkage)
    return float(np.sqrt(max(float(d @ np.linalg.solve(cov, d)), 0.0)))


def leave_one_out_mahalanobis(latents: np.ndarray, shrinkage: float = COVARIANCE_SHRINKAGE) -> np.ndarray:
    """(M,) Mahalanobis distance of each library latent against the other M - 1."""
    x = np.asarray(latents, dtype=np.float64)
    return np.array([latent_mahalanobis(x[i], np.delete(x, i, axis=0), shrinkage) for i in range(len(x))])


# ----------------------------------------------------------------------------- artefacts


def _edge_keys(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    return e[:, 0] * np.int64(n_vertices) + e[:, 1]


def mesh_genus(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Total genus of a closed triangle surface from its Euler characteristic.

    ``chi = V - E + F`` over the referenced vertices, unique edges and faces; with ``c``
    connected parts, ``genus = c - chi / 2`` (0 for sphere-like parts, 1 per handle or
    through-hole).

    Args:
        vertices: (V, 3). faces: (F, 3) int, a closed surface.
    """
    f = np.asarray(faces, dtype=np.int64)
    nv = len(vertices)
    used = np.unique(f)
    n_edges = len(np.unique(_edge_keys(f, nv)))
    chi = len(used) - n_edges + len(f)
    parts, _ = connected_vertex_parts(nv, np.concatenate([f[:, :2], f[:, 1:]]))
    parts -= nv - len(used)  # unreferenced vertices are parts of their own
    return int((2 * parts - chi) // 2)


def surface_parts(field: np.ndarray, grid: GridSpec, scales: Sequence[float] = (1.0, 1.0)) -> dict:
    """Closed parts of the raw marching-cubes surface and what the decoder's clean-up drops.

    Runs ``extract_surface`` without clean-up and applies the decoder's rule
    (``decode.MIN_PART_FRACTION``: parts under 1 % of the largest part's volume and cavities go).

    Args:
        field: (N, N, N) SDF on ``grid`` (unit-cube units, negative inside).
        grid: its grid. scales: (width, length) scales.
    Returns:
        ``parts_before_cleanup`` (closed surface parts), ``cavities`` (parts of negative volume),
        ``floating_parts`` (positive parts other than the largest), ``parts_after_cleanup``,
        ``dropped_volume_fraction`` (|volume| of the dropped parts over the solid volume),
        ``floating_volume_fraction`` (volume of the floating parts, kept or dropped, over the
        solid volume), ``volume_m3`` (solid volume before clean-up).
    """
    v, f = extract_surface(field, grid, (float(scales[0]), float(scales[1])), min_part_fraction=0.0)
    n_parts, label = connected_vertex_parts(len(v), np.concatenate([f[:, :2], f[:, 1:]]))
    face_part = label[f[:, 0]]
    tri = v[f]
    vol = np.bincount(face_part, weights=np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])),
                      minlength=n_parts) / 6.0
    keep = vol >= MIN_PART_FRACTION * vol.max()
    solid = float(vol[vol > 0].sum())
    positive = np.flatnonzero(vol > 0)
    floating = positive[positive != int(np.argmax(vol))]
    return {
        "parts_before_cleanup": int(n_parts),
        "cavities": int(np.sum(vol < 0)),
        "floating_parts": int(len(floating)),
        "parts_after_cleanup": int(keep.sum()),
        "dropped_volume_fraction": float(np.abs(vol[~keep]).sum() / solid),
        "floating_volume_fraction": float(vol[floating].sum() / solid),
        "volume_m3": solid,
    }


def robust_genus(field: np.ndarray, grid: GridSpec, scales: Sequence[float] = (1.0, 1.0),
                 offset_voxels: float = GENUS_OFFSET_VOXELS,
                 surface: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[int, int]:
    """Genus of the cleaned decoded surface, and the genus that survives small level offsets.

    A handle or tunnel narrower than about a voxel (a marching-cubes pinch) shows at one level
    only; a real through-hole shows at the zero level and at +- ``offset_voxels``. The robust
    genus is the smallest of the three.

    Args:
        field, grid, scales: as ``surface_parts``.
        offset_voxels: the level offset in voxels.
        surface: the cleaned zero-level mesh ``extract_surface(field, grid, scales)`` when the
            caller has it already (saves one marching cubes).
    Returns:
        (genus at the zero level, robust genus).
    """
    sc = (float(scales[0]), float(scales[1]))
    delta = np.float32(offset_voxels * grid.voxel)
    f = np.asarray(field, dtype=np.float32)
    zero = mesh_genus(*(surface if surface is not None else extract_surface(f, grid, sc)))
    return zero, min([zero] + [mesh_genus(*extract_surface(f + d, grid, sc)) for d in (-delta, delta)])


def _trilinear(vol: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of an (N, N, N) volume at (n, 3) index coordinates (clamped)."""
    n = vol.shape[0]
    q = np.clip(p, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(q).astype(np.int64), n - 2)
    t = q - i0
    flat = vol.ravel()
    base = (i0[:, 0] * n + i0[:, 1]) * n + i0[:, 2]
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = t[:, 0] if dx else 1.0 - t[:, 0]
        for dy in (0, 1):
            wy = t[:, 1] if dy else 1.0 - t[:, 1]
            for dz in (0, 1):
                wz = t[:, 2] if dz else 1.0 - t[:, 2]
                out += wx * wy * wz * flat[base + (dx * n + dy) * n + dz]
    return out


def _kept_inside(field: np.ndarray) -> np.ndarray:
    """(N, N, N) bool: inside nodes of the parts the decoder keeps (by node count, same 1 % rule)."""
    inside = field < 0
    try:
        from scipy.ndimage import label
    except ImportError:
        labels, n = _label_numpy(inside)
    else:
        labels, n = label(inside)
    size = np.bincount(labels.ravel(), minlength=n + 1)
    size[0] = 0
    keep = size >= MIN_PART_FRACTION * size.max()
    keep[0] = False
    return keep[labels]


def _label_numpy(inside: np.ndarray) -> tuple[np.ndarray, int]:
    """numpy-only ``scipy.ndimage.label`` (face adjacency; labels 1..n, 0 outside) for Blender."""
    idx = np.full(inside.shape, -1, dtype=np.int64)
    idx[inside] = np.arange(int(inside.sum()))
    pairs = []
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        both = inside[tuple(lo)] & inside[tuple(hi)]
        pairs.append(np.stack([idx[tuple(lo)][both], idx[tuple(hi)][both]], axis=1))
    n, lab = connected_vertex_parts(int(inside.sum()), np.concatenate(pairs))
    labels = np.zeros(inside.shape, dtype=np.int64)
    labels[inside] = lab + 1
    return labels, int(n)


def wall_thickness(field: np.ndarray, grid: GridSpec, scales: Sequence[float] = (1.0, 1.0),
                   n: int = WALL_SAMPLES, seed: Any = 0, step_m: float = WALL_STEP_M,
                   max_m: float = WALL_MAX_M) -> np.ndarray:
    """Wall thickness at surface samples: distance along the inward normal to where the ray leaves.

    Why rays (the "shape diameter" of Shapira et al. 2008, the usual wall-thickness check
    before 3-D printing) rather than twice the SDF along its medial ridge: the ridge meets the
    surface at every convex edge, so its minimum is ~0 on any box; a ray along the inward
    normal crosses the whole part there and is short only where the part is really thin.

    Surface samples are the zero crossings of the field on grid edges of the parts the decoder
    keeps (about uniform on the surface: the density varies by at most sqrt(3) with the normal).
    The normal is the field's gradient; rays march in metric steps through the trilinear field,
    with the width/length scales applied, until the field turns positive.

    Args:
        field: (N, N, N) SDF on ``grid``. grid: its grid. scales: (width, length).
        n: number of samples (all crossings if fewer). seed: sample choice.
        step_m, max_m: ray step and longest ray in metres.
    Returns:
        (n,) float64 thickness in metres (``max_m`` where the ray is still inside).
    """
    f = np.asarray(field, dtype=np.float64)
    kept = _kept_inside(f)
    pts = []
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        fa, fb = f[tuple(lo)], f[tuple(hi)]
        cross = ((fa < 0) != (fb < 0)) & (kept[tuple(lo)] | kept[tuple(hi)])
        at = np.argwhere(cross).astype(np.float64)
        at[:, ax] += fa[cross] / (fa[cross] - fb[cross])
        pts.append(at)
    p = np.concatenate(pts)
    if len(p) == 0:
        return np.zeros(0)
    if len(p) > n:
        p = p[np.sort(np.random.default_rng(seed).choice(len(p), n, replace=False))]
    # Metres per index step along x (length), y (width), z.
    m = grid.voxel * grid.extent_m * np.array([float(scales[1]), float(scales[0]), 1.0])
    grad = np.stack([_trilinear(f, p + 0.5 * e) - _trilinear(f, p - 0.5 * e) for e in np.eye(3)], axis=1) / m
    norm = np.linalg.norm(grad, axis=1, keepdims=True)
    inward = -grad / np.where(norm > 0, norm, 1.0)
    ts = np.arange(1, int(round(max_m / step_m)) + 1) * step_m
    ray = p[:, None, :] + ts[None, :, None] * (inward / m)[:, None, :]
    flat = ray.reshape(-1, 3)
    inside_grid = np.all((flat >= 0) & (flat <= f.shape[0] - 1), axis=1)
    val = np.ones(len(flat))  # outside the grid is outside the shape
    val[inside_grid] = _trilinear(f, flat[inside_grid])
    out = (val > 0).reshape(len(p), len(ts))
    first = np.where(out.any(axis=1), out.argmax(axis=1), len(ts) - 1)
    return ts[first]


def thinnest_wall(thickness: np.ndarray, percentile: float = WALL_PERCENTILE) -> float:
    """The ``percentile`` of the wall thickness samples, metres (the thinnest wall covering that
    share of the surface)."""
    t = np.asarray(thickness, dtype=np.float64)
    return float(np.percentile(t, percentile)) if len(t) else 0.0


# ----------------------------------------------------------------------------- dimensions


def mesh_dimensions(vertices: np.ndarray) -> np.ndarray:
    """(3,) bounding-box (length, width, height) of vertices in the vehicle frame, metres."""
    v = np.asarray(vertices, dtype=np.float64)
    return v.max(axis=0) - v.min(axis=0)


def _opened_max(coord: np.ndarray, value: np.ndarray, slice_m: float, window_m: float) -> float:
    """Largest ``value`` over slices of ``coord`` after a grey opening of the slice-wise maximum
    over ``window_m``: the highest level the profile holds over a whole window."""
    lo = coord.min()
    idx = np.floor((coord - lo) / slice_m).astype(np.int64)
    prof = np.full(int(idx.max()) + 1, -np.inf)
    np.maximum.at(prof, idx, value)
    w = max(1, int(round(window_m / slice_m)))
    if len(prof) < w:
        return float(value.max())
    from numpy.lib.stride_tricks import sliding_window_view

    eroded = sliding_window_view(prof, w).min(axis=1)  # eroded[i]: min over prof[i:i + w]
    padded = np.concatenate([np.full(w - 1, -np.inf), eroded, np.full(w - 1, -np.inf)])
    opened = sliding_window_view(padded, w).max(axis=1)  # max over the windows covering each slice
    best = float(opened.max())
    return best if np.isfinite(best) else float(value.max())


def body_dimensions(vertices: np.ndarray, faces: np.ndarray, window_m: float = BODY_WINDOW_M,
                    slice_m: float = BODY_SLICE_M, n_points: int = BODY_SAMPLE_POINTS, seed: Any = 0) -> np.ndarray:
    """(3,) length, width and height of the body without parts shorter than ``window_m``.

    Manufacturers' widths leave the door mirrors out, heights the antenna (docs/realism.md,
    "Dimensions against real vehicles"). Here the surface (``n_points`` samples plus the
    vertices) is sliced every ``slice_m`` along x; on each side the slice-wise extreme of y (and
    the top of z) is opened over ``window_m``, i.e. the profile keeps only levels it holds over
    a whole window, so a mirror 0.25 m long or an antenna does not widen or raise the body while
    a body side, a roof or a wheel arch longer than the window counts in full. The length is
    measured the same way on slices along y (a tow hook does not lengthen the car). A shape
    shorter than a window keeps its bounding box.

    Args:
        vertices: (V, 3) metres, vehicle frame. faces: (F, 3).
    Returns:
        (3,) float64 metres.
    """
    v = np.asarray(vertices, dtype=np.float64)
    p = np.concatenate([sample_surface(v, faces, n_points, seed), v]) if len(faces) else v
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    width = _opened_max(x, y, slice_m, window_m) + _opened_max(x, -y, slice_m, window_m)
    length = _opened_max(y, x, slice_m, window_m) + _opened_max(y, -x, slice_m, window_m)
    height = _opened_max(x, z, slice_m, window_m) - float(z.min())
    bbox = mesh_dimensions(v)
    return np.minimum(np.array([length, width, height]), bbox)


def dimension_excess(dims: Sequence[float], vehicle_class: str) -> np.ndarray:
    """(3,) relative amount by which (L, W, H) leaves the class's real range (0 inside).

    Below the range: ``(low - d) / low``; above: ``(d - high) / high``.

    Raises:
        ConfigError: a class without a range in ``DIMENSION_RANGES``.
    """
    if vehicle_class not in DIMENSION_RANGES:
        raise ConfigError(f"no real dimension range for class {vehicle_class!r} "
                          f"(known: {', '.join(DIMENSION_RANGES)})")
    d = np.asarray(dims, dtype=np.float64).reshape(3)
    rng = np.asarray(DIMENSION_RANGES[vehicle_class], dtype=np.float64)
    lo, hi = rng[:, 0], rng[:, 1]
    return np.maximum(np.maximum((lo - d) / lo, (d - hi) / hi), 0.0)


def plausible_classes(dims: Sequence[float]) -> list[str]:
    """Classes whose real (L, W, H) ranges all contain ``dims``, in ``DIMENSION_RANGES`` order."""
    return [c for c in DIMENSION_RANGES if not dimension_excess(dims, c).any()]


# ----------------------------------------------------------------------------- reference


@dataclass
class RealismReference:
    """What the measures compare a shape against: the asset set's CAD models and the library's
    own leave-one-out figures.

    Attributes:
        histogram: (BEV_BINS, BEV_BINS) int64 summed counts of ``points_per_model`` surface
            points of every CAD model (the paper's "histogram of all CAD models").
        points: (M, CHAMFER_POINTS, 3) float32 surface points per CAD model (metres).
        asset_ids: the M shape-space asset ids, in shape-space order.
        asset_classes: their vehicle classes.
        jsd_loo: (M,) JSD of each model's 1000-point sample against the histogram of the others.
        chamfer_loo: (M,) Chamfer distance (m) of each asset's decoded latent to the nearest
            *other* CAD model.
        mahalanobis_loo: (M,) Mahalanobis distance of each latent against the other latents.
        meta: parameters and provenance (bins, window_m, points_per_model, seed,
            shape_space_hash, library_fingerprint).
    """

    histogram: np.ndarray
    points: np.ndarray
    asset_ids: list[str]
    asset_classes: list[str]
    jsd_loo: np.ndarray
    chamfer_loo: np.ndarray
    mahalanobis_loo: np.ndarray
    meta: dict = field(default_factory=dict)
    source: Path | None = None
    _trees: list | None = field(default=None, init=False, repr=False, compare=False)
    _sorted: list | None = field(default=None, init=False, repr=False, compare=False)

    def chamfer_distances(self, points: np.ndarray) -> np.ndarray:
        """(M,) symmetric Chamfer distance (m) of a (n, 3) sample to every CAD model's points.

        With numba, the compiled sweep of :mod:`.nearest` (the same bits as the trees of
        :meth:`chamfer_distances_tree`, ~2.5x faster); without it, or for non-finite points,
        the trees."""
        sweep = _nearest_module()
        q = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if sweep is None or len(q) == 0 or not np.isfinite(q).all() or not np.isfinite(self.points).all():
            return self.chamfer_distances_tree(q)
        ref = np.ascontiguousarray(self.points, dtype=np.float64)
        if self._sorted is None:
            self._sorted = [sweep.sort_by_x(p) for p in ref]
        qs = sweep.sort_by_x(q)
        nn = sweep.nn_distances_sorted
        return np.array([float(0.5 * (nn(q, self._sorted[j]).mean() + nn(ref[j], qs).mean()))
                         for j in range(len(ref))])

    def chamfer_distances_tree(self, points: np.ndarray) -> np.ndarray:
        """:meth:`chamfer_distances` with a ``cKDTree`` per cloud (the definition the sweep is
        tested against; the path without numba)."""
        ref = self.points.astype(np.float64)
        if self._trees is None:
            self._trees = [_kdtree(p) for p in ref]
        q = np.asarray(points, dtype=np.float64)
        tq = _kdtree(q)
        return np.array([chamfer_distance(q, ref[j], tq, self._trees[j]) for j in range(len(ref))])

    @property
    def jsd_limit(self) -> float:
        """Largest leave-one-out JSD of the library: a shape scoring above is less like the
        asset set than any of its own members."""
        return float(self.jsd_loo.max())

    @property
    def chamfer_limit_m(self) -> float:
        return float(self.chamfer_loo.max())

    @property
    def mahalanobis_limit(self) -> float:
        return float(self.mahalanobis_loo.max())

    def _meta(self) -> dict:
        meta = dict(self.meta)
        meta.update({
            "format": REFERENCE_FORMAT,
            "version": REFERENCE_VERSION,
            "asset_classes": list(self.asset_classes),
            "jsd_loo": [float(x) for x in self.jsd_loo],
            "chamfer_loo": [float(x) for x in self.chamfer_loo],
            "mahalanobis_loo": [float(x) for x in self.mahalanobis_loo],
        })
        return meta

    def to_bytes(self) -> bytes:
        """The exact bytes of the ``.npz`` file (deterministic: fixed order and timestamps)."""
        members = {
            "meta": np.asarray(json.dumps(self._meta(), indent=1, sort_keys=True, allow_nan=False)),
            "histogram": np.ascontiguousarray(self.histogram, dtype=np.int64),
            "points": np.ascontiguousarray(self.points, dtype=np.float32),
            "asset_ids": np.asarray(self.asset_ids, dtype=f"<U{max([1] + [len(a) for a in self.asset_ids])}"),
        }
        return npz_bytes({name: members[name] for name in _MEMBERS})

    def save(self, path: str | Path = DEFAULT_REFERENCE) -> Path:
        """Write the ``.npz`` atomically; returns the path."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes())
        return path

    def matches(self, space) -> bool:
        """Whether this reference was built for ``space`` (same content hash)."""
        return self.meta.get("shape_space_hash") == space.content_hash


def build_reference(library, space, progress: bool = False) -> RealismReference:
    """Compute the reference from the library's CAD meshes and the shape space (~2 s).

    Args:
        library: the ``VehicleLibrary`` the space was built from.
        space: the ``ShapeSpace``; its asset ids name the CAD models.
    """
    from .library import load_asset_mesh

    ids = list(space.asset_ids)
    m = len(ids)
    if m < 2:
        raise ConfigError("the realism reference needs at least two shape-space assets (leave-one-out)")
    items = list(enumerate(ids))
    if progress:
        from ..progress import progress as bar

        items = bar(items, desc="realism reference", unit="asset")
    hists = np.zeros((m, BEV_BINS, BEV_BINS), dtype=np.int64)
    points = np.zeros((m, CHAMFER_POINTS, 3), dtype=np.float32)
    own = []  # each CAD model's 1000-point query sample (seed 0, as a query)
    for i, aid in items:
        mesh = load_asset_mesh(library, aid)
        v, f = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        ref = footprint_centred(sample_surface(v, f, REFERENCE_POINTS_PER_MODEL, [REFERENCE_SEED, i]), v)
        hists[i] = bev_histogram(ref)
        points[i] = ref[:CHAMFER_POINTS]
        own.append(footprint_centred(sample_surface(v, f, N_POINTS, 0), v))
    total = hists.sum(axis=0)
    jsd_loo = np.array([jsd(bev_histogram(own[i]), total - hists[i]) for i in range(m)])
    classes = [library.get(a).vehicle_class for a in ids]
    meta = {
        "bins": BEV_BINS,
        "window_m": BEV_WINDOW_M,
        "points_per_model": REFERENCE_POINTS_PER_MODEL,
        "query_points": N_POINTS,
        "seed": REFERENCE_SEED,
        "covariance_shrinkage": COVARIANCE_SHRINKAGE,
        "shape_space_hash": space.content_hash,
        "library_fingerprint": space.build.get("library_fingerprint", ""),
    }
    ref = RealismReference(histogram=total, points=points, asset_ids=ids, asset_classes=classes,
                           jsd_loo=jsd_loo, chamfer_loo=np.zeros(m),
                           mahalanobis_loo=leave_one_out_mahalanobis(space.latents), meta=meta)
    for i in range(m):  # each library vehicle as the shape space decodes it, against the other models
        v, f = space.decode_latent(space.latents[i])
        d = ref.chamfer_distances(footprint_centred(sample_surface(v, f, N_POINTS, 0), v))
        ref.chamfer_loo[i] = np.delete(d, i).min()
    return ref


def load_reference(path: str | Path = DEFAULT_REFERENCE) -> RealismReference:
    """Load and validate a reference file.

    Raises:
        FileFormatError: missing or corrupt file, or a field not matching the contract.
    """
    arrays = read_npz(path, "realism reference .npz", " (build it with `adv3d shapes realism-reference`)")
    arrays.require(_MEMBERS)
    meta_node = arrays.json("meta")
    meta = meta_node.object()
    check_header(meta_node, REFERENCE_FORMAT, (REFERENCE_VERSION,))
    if meta.get("bins") != BEV_BINS or meta.get("window_m") != BEV_WINDOW_M:
        meta_node["bins"].fail(f"bins {BEV_BINS} and window_m {BEV_WINDOW_M} (this code's histogram)",
                               f"{meta.get('bins')}, {meta.get('window_m')}")
    ids = arrays.array("asset_ids", kind="U", ndim=1)
    if len(ids) < 2:
        arrays.fail("asset_ids", "at least 2 asset ids", len(ids))
    m = len(ids)
    hist = arrays.array("histogram", dtype=np.int64, shape=(BEV_BINS, BEV_BINS))
    if (hist < 0).any():
        arrays.fail("histogram", "non-negative counts", int(hist.min()))
    pts = arrays.array("points", dtype=np.float32, shape=(m, CHAMFER_POINTS, 3), finite=True)
    if np.abs(pts).max(initial=0.0) > 100.0:  # footprint-centred vehicle surfaces, metres
        arrays.fail("points", "surface points within 100 m of the footprint centre", float(np.abs(pts).max()))
    loo = {key: meta_node[key].numbers(length=m, lo=0.0) for key in ("jsd_loo", "chamfer_loo", "mahalanobis_loo")}
    classes = [c.string() for c in meta_node["asset_classes"].items(length=m)]
    keep = {k: v for k, v in meta.items() if k not in ("format", "version", "asset_classes", *loo)}
    return RealismReference(histogram=hist, points=pts, asset_ids=[str(x) for x in ids], asset_classes=classes,
                            meta=keep, source=Path(path), **loo)


_CACHE: dict[str, RealismReference] = {}


def reference_cache_dir() -> Path:
    """Where references built for shape spaces other than the shipped one are kept, one
    ``.npz`` per shape-space content hash: ``$ADV3D_CACHE/realism``, else
    ``$XDG_CACHE_HOME/adv3d/realism`` (``~/.cache/adv3d/realism``)."""
    from ..fileio import user_cache_dir

    return user_cache_dir() / "realism"


def cached_reference_path(space) -> Path:
    """The cache file of ``space``'s reference (named by its content hash)."""
    return reference_cache_dir() / f"{space.content_hash.split(':')[-1][:32]}.npz"


def known_reference(space) -> RealismReference | None:
    """``space``'s reference when one exists without building: this process's, the shipped file
    (built for the shipped space) or the content-keyed cache file (:func:`cached_reference_path`,
    written by :func:`cache_reference`); None otherwise. A cache file that is unreadable or was
    built for another space is ignored (it is rebuilt)."""
    key = space.content_hash
    if key in _CACHE:
        return _CACHE[key]
    for path in (DEFAULT_REFERENCE, cached_reference_path(space)):
        if path.exists():
            try:
                ref = load_reference(path)
            except ConfigError:
                continue
            if ref.matches(space):
                _CACHE[key] = ref
                return ref
    return None


def cache_reference(space, reference: RealismReference) -> Path | None:
    """Keep ``reference`` for ``space`` in this process and in the cache folder (atomic write;
    None when the folder cannot be written: the reference is then rebuilt next session)."""
    _CACHE[space.content_hash] = reference
    path = cached_reference_path(space)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return reference.save(path)
    except OSError:
        return None


def default_reference(space, library=None) -> RealismReference:
    """The reference for ``space``: a known one (:func:`known_reference`: the shipped file for
    the shipped space, else the content-keyed cache), else built from ``library`` (the
    ``VehicleLibrary`` the space was built from; default the bundled one) and cached.

    Raises:
        ConfigError: no known reference and the library lacks the space's assets.
    """
    ref = known_reference(space)
    if ref is None:
        from .library import load_library

        try:
            ref = build_reference(library if library is not None else load_library(), space)
        except KeyError as exc:
            raise ConfigError(f"no realism reference for this shape space: {exc}") from None
        cache_reference(space, ref)
    return ref


# ----------------------------------------------------------------------------- report


def shape_surface_measures(vertices: np.ndarray, faces: np.ndarray, reference: RealismReference,
                           vehicle_class: str | None = None, seed: Any = 0) -> dict:
    """The measures any metric vehicle mesh has: JSD, nearest CAD model, dimensions.

    Args:
        vertices: (V, 3) metres, vehicle frame (+x front, z up). faces: (F, 3).
        reference: what to compare against.
        vehicle_class: class whose real dimensions apply; default the nearest CAD model's class.
        seed: surface sample seed.
    Returns:
        ``dimensions_m`` is the bounding box, checked against the class (a decoded shape of the
        shape space: what the attack's class-scale region bounds); ``body_dimensions_m``
        (``body_dimensions``: without mirrors) is what ``mesh_realism_report`` checks for a
        source mesh.
    """
    v = np.asarray(vertices, dtype=np.float64)
    pts = footprint_centred(sample_surface(v, faces, N_POINTS, seed), v)
    dists = reference.chamfer_distances(pts)
    near = int(np.argmin(dists))
    dims = mesh_dimensions(v)
    body = body_dimensions(v, faces, seed=seed)
    cls = vehicle_class or reference.asset_classes[near]
    excess = dimension_excess(dims, cls)
    return {
        "jsd": jsd(bev_histogram(pts), reference.histogram),
        "nearest_asset": reference.asset_ids[near],
        "nearest_chamfer_m": float(dists[near]),
        "dimensions_m": [float(x) for x in dims],
        "body_dimensions_m": [float(x) for x in body],
        "dimension_class": cls,
        "dimension_excess": [float(x) for x in excess],
        "plausible_classes": plausible_classes(dims),
    }


def quick_measures(vertices: np.ndarray, faces: np.ndarray, reference: RealismReference, *,
                   latent: Any = None, latents: np.ndarray | None = None, vehicle_class: str | None = None,
                   chamfer: bool = True, seed: Any = 0, limits: RealismLimits | None = None) -> dict:
    """The cheap realism figures of a metric mesh: what every attack query carries and what the
    add-on shows live (docs/realism.md, "Per query and live").

    The paper's JSD (the same sample and value as the full report), the dimensions against the
    class's real ranges, the nearest CAD model by Chamfer distance (``chamfer``) and the latent
    Mahalanobis distance (when ``latent`` is given). Leaves out what needs the decoder's field
    (parts, genus, wall thickness): those cost ~3x more and are computed for best shapes only.

    Args:
        vertices: (V, 3) metres, vehicle frame. faces: (F, 3).
        reference: what to compare against.
        latent: (K,) latent of the shape, or None (a mesh from outside the shape space).
        latents: (M, K) library latents, in ``reference.asset_ids`` order (needed with ``latent``).
        vehicle_class: class whose real dimensions apply; default the nearest CAD model's class
            (by Chamfer, else by latent distance); without either, no dimension check.
        chamfer: compute the nearest CAD model (~25 ms with scipy, ~50 ms without).
        seed: surface sample seed (0: the full report's sample).
        limits: the limits to check (default ``LIMITS``).
    Returns:
        a JSON-able dict: ``jsd``, [``nearest_asset``, ``nearest_chamfer_m``], [``mahalanobis``],
        ``dimensions_m``, ``dimension_class``, ``dimension_excess`` (None without a class),
        ``flags`` (the failed checks among those measured, named as in the full report).
    """
    v = np.asarray(vertices, dtype=np.float64)
    lim = (limits or LIMITS).resolve(reference, 0.0)
    pts = footprint_centred(sample_surface(v, faces, N_POINTS, seed), v)
    out: dict[str, Any] = {"jsd": jsd(bev_histogram(pts), reference.histogram)}
    nearest_class = None
    if chamfer:
        dists = reference.chamfer_distances(pts)
        near = int(np.argmin(dists))
        out["nearest_asset"], out["nearest_chamfer_m"] = reference.asset_ids[near], float(dists[near])
        nearest_class = reference.asset_classes[near]
    if latent is not None:
        if latents is None:
            raise ConfigError("quick_measures: a latent needs the library latents")
        z = np.asarray(latent, dtype=np.float64).reshape(-1)
        out["mahalanobis"] = latent_mahalanobis(z, latents)
        if nearest_class is None:
            nearest_class = reference.asset_classes[int(np.argmin(np.linalg.norm(latents - z[None], axis=1)))]
    body = body_dimensions(v, faces, seed=seed)
    cls = vehicle_class or nearest_class
    out["dimensions_m"] = [float(x) for x in mesh_dimensions(v)]
    out["body_dimensions_m"] = [float(x) for x in body]
    out["dimension_class"] = cls
    out["dimension_excess"] = None
    if cls is not None:
        out["dimension_excess"] = [float(x) for x in dimension_excess(out["dimensions_m"], cls)]
    out["flags"] = check_flags(out, lim)
    return out


def field_measures(field: np.ndarray, grid: GridSpec, scales: Sequence[float], vertices: np.ndarray,
                   faces: np.ndarray, reference: RealismReference, vehicle_class: str | None = None,
                   seed: Any = 0) -> dict:
    """The figures of a decoded field and its surface: mesh measures (JSD, nearest, dimensions)
    on the surface, parts, genus and wall thickness on the field (docs/realism.md).

    Args:
        field: (N, N, N) SDF on ``grid``; scales: (width, length) applied to it.
        vertices, faces: the cleaned zero-level surface ``extract_surface(field, grid, scales)``.
    """
    sc = (float(scales[0]), float(scales[1]))
    report = shape_surface_measures(vertices, faces, reference, vehicle_class, seed)
    report.update(surface_parts(field, grid, sc))
    report["genus"], report["genus_robust"] = robust_genus(field, grid, sc, surface=(vertices, faces))
    thick = wall_thickness(field, grid, sc, seed=seed)
    voxel_m = grid.voxel * grid.extent_m
    report["thinnest_wall_m"] = thinnest_wall(thick)
    report["thin_wall_fraction"] = float(np.mean(thick < voxel_m)) if len(thick) else 0.0
    return report


def _verdict(report: dict, reference: RealismReference, voxel_m: float, limits: RealismLimits | None) -> dict:
    report["limits"] = (limits or LIMITS).resolve(reference, voxel_m)
    report["flags"] = check_flags(report, report["limits"])
    report["realistic"] = not report["flags"]
    return report


def latent_realism_report(space, z: Any, scales: Sequence[float] = (1.0, 1.0),
                          reference: RealismReference | None = None, vehicle_class: str | None = None,
                          seed: Any = 0, limits: RealismLimits | None = None) -> dict:
    """Every realism figure of the shape ``(z, scales)`` of ``space`` (any finite z).

    Args:
        limits: the limits to check (default ``LIMITS``, the calibrated ones).
    Returns:
        a JSON-able dict: the figures (see docs/realism.md), the limits they are checked
        against, ``flags`` (names of the failed checks) and ``realistic`` (no flag).
    Raises:
        EmptySurfaceError: the latent decodes to no surface.
    """
    ref = reference if reference is not None else default_reference(space)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    sc = (float(scales[0]), float(scales[1]))
    field_ = space.decode_sdf(z)
    v, f = space.decode_latent(z, sc)
    report = field_measures(field_, space.grid, sc, v, f, ref, vehicle_class, seed)
    latent_d = np.linalg.norm(space.latents - z[None, :], axis=1)
    report["nearest_latent_asset"] = space.asset_ids[int(np.argmin(latent_d))]
    report["nearest_latent_distance"] = float(latent_d.min())
    report["mahalanobis"] = latent_mahalanobis(z, space.latents)
    return _verdict(report, ref, space.grid.voxel * space.grid.extent_m, limits)


def mesh_fit_scales(vertices: np.ndarray, grid: GridSpec) -> tuple[float, float]:
    """(width, length) scales that bring a metric mesh inside the grid's vehicle box.

    The box is the largest asset the grid was sized for (cube edge / ``SCALE_MARGIN``); a
    longer or wider mesh is shrunk along that axis only and its SDF measured with the scale put
    back, as the shape space's own width and length scales are. Height has no scale.
    """
    from .sdf import SCALE_MARGIN

    box = grid.extent_m / SCALE_MARGIN
    d = mesh_dimensions(vertices)
    return max(1.0, float(d[1]) / box), max(1.0, float(d[0]) / box)


def mesh_realism_report(space, vertices: np.ndarray, faces: np.ndarray, reference: RealismReference | None = None,
                        vehicle_class: str | None = None, seed: Any = 0, limits: RealismLimits | None = None,
                        field: np.ndarray | None = None) -> dict:
    """The whole realism report of any metric vehicle mesh: SDF, decode, every check.

    The mesh (vehicle frame: metres, +x front, z up, footprint centre at the origin on the
    ground, as ``mesh_io.import_vehicle`` gives) goes through what the shape space does to its
    own assets: the SDF on the space's grid by the space's method (``sdf.sdf_volume``, panels
    seen from outside along less than ``MESH_MIN_VISIBILITY`` of their rays out of the sign; a mesh
    longer or wider than the grid's vehicle box is scaled into it, ``mesh_fit_scales``), the
    zero level decoded by the decoder (``decode.extract_surface``), the latent by projection
    (``ShapeSpace.encode``). Then the figures of ``latent_realism_report`` on that field and
    surface, and what the SDF kept of the source: ``source_dimensions_m`` (its bounding box),
    ``source_body_dimensions_m``, ``dropped_extent_m`` (bounding box lost per axis: thin parts
    the grid did not keep, e.g. mirrors when not captured) and ``outside_source_m`` (largest and
    99th-percentile distance from the decoded surface to the source surface: solid that is not
    the vehicle's). The dimension check uses the source's body dimensions
    (``body_dimensions_m``; the decoded surface's are ``decoded_body_dimensions_m``).

    Args:
        space: the ``ShapeSpace``.
        vertices: (V, 3) metres. faces: (F, 3).
        field: the SDF when the caller has it (same grid, scales from ``mesh_fit_scales``).
    Raises:
        Adv3dError: the mesh is taller than the grid or encloses no volume on it.
    """
    from .sdf import sdf_volume, unsigned_distance

    ref = reference if reference is not None else default_reference(space)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    sc = mesh_fit_scales(v, space.grid)
    if field is None:
        vs = v.copy()
        vs[:, 0] /= sc[1]
        vs[:, 1] /= sc[0]
        vis = MESH_MIN_VISIBILITY if space.method == "winding" else 0.0
        field = sdf_volume(vs, f, space.grid, space.method, min_visibility=vis)
    dv, df = extract_surface(field, space.grid, sc)
    report = field_measures(field, space.grid, sc, dv, df, ref, vehicle_class, seed)
    z = space.encode(field)
    latent_d = np.linalg.norm(space.latents - z[None, :], axis=1)
    report["latent"] = [float(x) for x in z]
    report["scales"] = [float(x) for x in sc]
    report["nearest_latent_asset"] = space.asset_ids[int(np.argmin(latent_d))]
    report["nearest_latent_distance"] = float(latent_d.min())
    report["mahalanobis"] = latent_mahalanobis(z, space.latents)
    src = mesh_dimensions(v)
    src_body = body_dimensions(v, f, seed=seed)
    report["source_dimensions_m"] = [float(x) for x in src]
    report["source_body_dimensions_m"] = [float(x) for x in src_body]
    # the class check on the source's body: the 9.6 cm grid decodes sides 2-3 cm inwards, an
    # error of the representation, not of the vehicle (the decoded figures stay in the report)
    report["decoded_body_dimensions_m"] = report["body_dimensions_m"]
    report["body_dimensions_m"] = report["source_body_dimensions_m"]
    report["dimension_excess"] = [float(x) for x in dimension_excess(src_body, report["dimension_class"])]
    report["plausible_classes"] = plausible_classes(src_body)
    report["dropped_extent_m"] = [float(max(0.0, a - b)) for a, b in zip(src, report["dimensions_m"])]
    # decoded surface placed as the source: both are footprint-centred on the ground, but the
    # decoder centres on its largest part; align by bounding-box centres of the two
    shift = 0.5 * (v.min(axis=0) + v.max(axis=0)) - 0.5 * (dv.min(axis=0) + dv.max(axis=0))
    shift[2] = v[:, 2].min() - dv[:, 2].min()
    far = unsigned_distance(v, f, dv + shift)
    report["outside_source_m"] = [float(far.max()), float(np.percentile(far, 99))]
    return _verdict(report, ref, space.grid.voxel * space.grid.extent_m, limits)


def realism_report(space, u: Any, reference: RealismReference | None = None,
                   vehicle_class: str | None = None, seed: Any = 0, limits: RealismLimits | None = None) -> dict:
    """Every realism figure of the unit vector ``u`` of ``space`` (see ``latent_realism_report``).

    Costs ~0.1-0.2 s per shape on one core (bench/realism.py measures it): four marching cubes
    (the surface, the raw surface, two level offsets), 1000 rays, 18 Chamfer distances.
    """
    z, scales = space.unit_to_latent(u)
    return latent_realism_report(space, z, scales, reference, vehicle_class, seed, limits)
