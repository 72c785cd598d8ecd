"""Signed distance volume -> metric vehicle mesh (the hot path of every attack query).

Marching cubes runs on the volume padded by one layer of a positive ("outside") value, so the
surface is closed even where a shape touches the grid border. Numpy + scikit-image only (scipy
for part labels where it is installed, see ``cleaning.connected_vertex_parts``): the Blender
add-on calls this in-process for live latent sliders.

The decoded vehicle is placed by the footprint of its *body*, its largest closed part, so a
small blob beside it (kept or dropped) never shifts the car. What the clean-up drops is
counted: ``extract_surface(..., info=d)`` fills ``d`` with the part counts and volumes, and
each drop is logged (logger ``adv3d_runner.shapes.decode``, level INFO).
"""
from __future__ import annotations

import logging

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

logger = logging.getLogger(__name__)


def _parts(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Part label per face (F,) and signed volume x 6 per part (P,), in ``v``'s units."""
    n_parts, label = connected_vertex_parts(len(v), np.concatenate([f[:, :2], f[:, 1:]]))
    face_part = label[f[:, 0]]
    # Signed volume per part: sum of tetrahedra against the origin (divergence theorem).
    tri = v[f]
    vol6 = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    return face_part, np.bincount(face_part, weights=vol6, minlength=n_parts)


def _keep_faces(v: np.ndarray, f: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces ``keep`` (F,) bool, with unused vertices removed."""
    f = f[keep]
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def extract_surface(
    field: np.ndarray,
    grid: GridSpec,
    scales: tuple[float, float] = (1.0, 1.0),
    min_part_fraction: float = MIN_PART_FRACTION,
    info: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of ``field`` as a metric mesh in the vehicle convention.

    Args:
        field: (N, N, N) SDF in unit-cube units on ``grid`` (negative inside).
        grid: the grid the field is sampled on.
        scales: (width_scale, length_scale) applied to y and x after metric scaling.
        min_part_fraction: drop closed parts smaller than this fraction of the largest one and
            cavities; 0 keeps the raw marching-cubes surface.
        info: if a dict, filled with ``parts`` (closed parts of the raw surface),
            ``dropped_parts`` (small parts dropped), ``dropped_cavities``, ``dropped_volume_m3``
            (|volume| of everything dropped), ``kept_parts``, ``volume_m3`` (of what is kept)
            and ``body_volume_m3`` (the largest part, which places the vehicle).
    Returns:
        vertices (V, 3) float64 metres: x/y origin at the centre of the body's footprint (the
        x/y bounding box of the largest closed part), the lowest point at z = 0; faces (F, 3)
        int64, counter-clockwise seen from outside.
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
    # Node index -> unit cube (undo the pad) -> metres, then the requested width/length scales.
    v = verts.astype(np.float64)
    v -= 1.0
    v *= grid.voxel
    v -= 0.5
    v = grid.to_metric(v)
    v[:, 0] *= float(scales[1])
    v[:, 1] *= float(scales[0])
    face_part, vol6 = _parts(v, faces)
    body = int(np.argmax(vol6))
    stats = {"parts": int(len(vol6)), "dropped_parts": 0, "dropped_cavities": 0, "dropped_volume_m3": 0.0}
    keep_part = np.ones(len(vol6), dtype=bool)
    if min_part_fraction > 0 and len(vol6) > 1:
        keep_part = vol6 >= min_part_fraction * vol6[body]
        if not keep_part.all():
            stats["dropped_parts"] = int(np.sum(~keep_part & (vol6 >= 0)))
            stats["dropped_cavities"] = int(np.sum(vol6 < 0))
            stats["dropped_volume_m3"] = float(np.abs(vol6[~keep_part]).sum() / 6.0)
            logger.info("decode: dropped %d small part(s) and %d cavity(ies), %.3g m^3 of %.3g m^3",
                        stats["dropped_parts"], stats["dropped_cavities"], stats["dropped_volume_m3"],
                        float(vol6[keep_part].sum() / 6.0))
            keep = keep_part[face_part]
            v, faces = _keep_faces(v, faces, keep)
            face_part = face_part[keep]
            vol6 = np.where(keep_part, vol6, 0.0)
    # Place by the body: a blob beside it must not move the car (its x/y box would).
    body_v = v[np.unique(faces[face_part == body])]
    bmn, bmx = body_v.min(axis=0), body_v.max(axis=0)
    v[:, 0] -= 0.5 * (bmn[0] + bmx[0])
    v[:, 1] -= 0.5 * (bmn[1] + bmx[1])
    v[:, 2] -= v[:, 2].min()
    if info is not None:
        info.update(stats)
        info["kept_parts"] = int(keep_part.sum())
        info["volume_m3"] = float(vol6.sum() / 6.0)
        info["body_volume_m3"] = float(vol6[body] / 6.0)
    # skimage's "descent" winding, with our (i, j, k) = (x, y, z) layout and a negative-inside
    # field, is counter-clockwise seen from outside (tests check the volume is positive).
    return v, np.ascontiguousarray(faces)
