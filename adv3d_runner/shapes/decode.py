"""Signed distance volume -> metric vehicle mesh (the hot path of every attack query).

Marching cubes runs on the volume padded by one layer of a positive ("outside") value, so the
surface is closed even where a shape touches the grid border. Numpy + scikit-image only (scipy
for part labels where it is installed, see ``cleaning.connected_vertex_parts``): the Blender
add-on calls this in-process for live latent sliders.
"""
from __future__ import annotations

import numpy as np

from ..errors import EmptySurfaceError
from .cleaning import connected_vertex_parts
from .sdf import GridSpec

#: Field values closer to zero than this fraction of a voxel are pushed to +-it before marching
#: cubes: an exact zero on a grid node makes several edge vertices coincide and produces
#: zero-area triangles. It moves the surface by at most 1e-3 voxel (< 0.1 mm).
_ZERO_NUDGE = 1e-3


#: Closed parts of the decoded surface enclosing less than this fraction of the largest part's
#: volume are dropped, as are cavities (parts with negative volume). PCA blends leave such
#: crumbs near the latent-box corners (over half of random queries have one, with ~0.03 % of the
#: volume); a LiDAR sees them as stray points in the air.
MIN_PART_FRACTION = 0.01


def _drop_small_parts(v: np.ndarray, f: np.ndarray, min_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Keep the closed parts enclosing >= ``min_fraction`` of the largest part's volume."""
    nv = len(v)
    edges = np.concatenate([f[:, :2], f[:, 1:]])
    n_parts, label = connected_vertex_parts(nv, edges)
    if n_parts == 1:
        return v, f
    face_part = label[f[:, 0]]
    # Signed volume per part: sum of tetrahedra against the origin (divergence theorem).
    tri = v[f]
    vol6 = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    part_vol = np.bincount(face_part, weights=vol6, minlength=n_parts)
    keep_part = part_vol >= min_fraction * part_vol.max()
    keep = keep_part[face_part]
    if keep.all():
        return v, f
    f = f[keep]
    used = np.zeros(nv, dtype=bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def extract_surface(
    field: np.ndarray,
    grid: GridSpec,
    scales: tuple[float, float] = (1.0, 1.0),
    min_part_fraction: float = MIN_PART_FRACTION,
) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of ``field`` as a metric mesh in the vehicle convention.

    Args:
        field: (N, N, N) SDF in unit-cube units on ``grid`` (negative inside).
        grid: the grid the field is sampled on.
        scales: (width_scale, length_scale) applied to y and x after metric scaling.
        min_part_fraction: drop closed parts smaller than this fraction of the largest one and
            cavities; 0 keeps the raw marching-cubes surface.
    Returns:
        vertices (V, 3) float64 metres, origin at the footprint (x/y bounding box) centre with
        the lowest point at z = 0; faces (F, 3) int64, counter-clockwise seen from outside.
    Raises:
        EmptySurfaceError: the field has no zero crossing (all inside or all outside).
    """
    from skimage.measure import marching_cubes

    f = np.asarray(field, dtype=np.float32)
    lo, hi = float(f.min()), float(f.max())
    if not (lo < 0.0 < hi) or not (np.isfinite(lo) and np.isfinite(hi)):
        raise EmptySurfaceError(
            f"decoded field has no surface (values in [{lo:.4g}, {hi:.4g}], need both signs)"
        )
    nudge = np.float32(_ZERO_NUDGE * grid.voxel)
    vol = np.pad(f, 1, mode="constant", constant_values=np.float32(grid.truncation))
    near = np.abs(vol) < nudge
    if near.any():
        vol[near] = np.where(vol[near] < 0, -nudge, nudge)
    verts, faces, _normals, _values = marching_cubes(
        vol, level=0.0, method="lewiner", step_size=1, allow_degenerate=True, gradient_direction="descent"
    )
    faces = faces.astype(np.int64, copy=False)
    if min_part_fraction > 0:
        verts, faces = _drop_small_parts(verts, faces, min_part_fraction)
    # Node index -> unit cube (undo the pad) -> metres, then the requested width/length scales.
    v = verts.astype(np.float64)
    v -= 1.0
    v *= grid.voxel
    v -= 0.5
    v = grid.to_metric(v)
    v[:, 0] *= float(scales[1])
    v[:, 1] *= float(scales[0])
    mn = v.min(axis=0)
    mx = v.max(axis=0)
    v[:, 0] -= 0.5 * (mn[0] + mx[0])
    v[:, 1] -= 0.5 * (mn[1] + mx[1])
    v[:, 2] -= mn[2]
    # skimage's "descent" winding, with our (i, j, k) = (x, y, z) layout and a negative-inside
    # field, is counter-clockwise seen from outside (tests check the volume is positive).
    return v, np.ascontiguousarray(faces)
