"""Set-level realism of found shapes against the library: MMD, COV and 1-NNA with the Chamfer
distance as PointFlow defines them (Yang et al., ICCV 2019, "PointFlow: 3D Point Cloud
Generation with Continuous Normalizing Flows", section 5.2), and the paper's set JSD named as
the Jensen-Shannon *distance* it is (docs/realism.md, "Set-level realism").

With S_g the found (generated) set, S_r the reference set and D the Chamfer distance:

- ``MMD(S_g, S_r) = 1/|S_r| sum_{Y in S_r} min_{X in S_g} D(X, Y)``: how close the found shapes
  come to each reference shape (fidelity; lower is better).
- ``COV(S_g, S_r) = |{argmin_{Y in S_r} D(X, Y) : X in S_g}| / |S_r|``: the share of reference
  shapes that are the nearest neighbour of some found shape (coverage; higher is better).
- ``1-NNA(S_g, S_r) = (sum_{X in S_g} 1[N_X in S_g] + sum_{Y in S_r} 1[N_Y in S_r]) /
  (|S_g| + |S_r|)``, N_X the nearest neighbour of X in ``S_g u S_r \\ {X}``: the leave-one-out
  accuracy of a 1-nearest-neighbour classifier telling the sets apart; 0.5 when they are alike,
  1 when every shape's neighbour is of its own set.
- ``D(X, Y) = mean_x min_y |x - y|^2 + mean_y min_x |x - y|^2``: PointFlow's Chamfer distance as
  its evaluation code computes it (means of squared distances; the paper writes sums, which for
  equal point counts is the same ranking times the count). Square metres; not the project's
  per-shape ``realism.chamfer_distance`` (halved, not squared, metres).

Shapes are compared in metres in the vehicle frame, footprint-centred (the project's metric
normalisation, docs/realism.md), not rescaled to a unit box as PointFlow does for ShapeNet: size
is what makes a 1.36 m-wide sedan unrealistic.

The set JSD: PointFlow computes the Jensen-Shannon *divergence* (base 2) of occupancy grids; the
Adv3D paper's JSD (a BEV histogram) follows LiDARGen's code, which returns
``scipy.spatial.distance.jensenshannon``, the square root of the divergence in nats: a distance.
``set_jsd_distance`` is the latter, pooled over the set (the BEV histogram of all found shapes'
points against the library's).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import ConfigError
from .realism import _nn_distances, bev_histogram, jsd


def pointflow_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """PointFlow's Chamfer distance of two (n, 3) / (m, 3) point sets, m^2:
    ``mean_a min_b |a - b|^2 + mean_b min_a |a - b|^2``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(np.mean(_nn_distances(a, b) ** 2) + np.mean(_nn_distances(b, a) ** 2))


def chamfer_matrix(found: Sequence[np.ndarray], reference: Sequence[np.ndarray]) -> np.ndarray:
    """(|found|, |reference|) PointFlow Chamfer distances, m^2."""
    return np.array([[pointflow_chamfer(x, y) for y in reference] for x in found], dtype=np.float64).reshape(
        len(found), len(reference))


def mmd_cov_1nna(d_gr: np.ndarray, d_gg: np.ndarray, d_rr: np.ndarray) -> dict:
    """MMD, COV and 1-NNA from the three distance matrices (PointFlow's definitions).

    Args:
        d_gr: (G, R) distances found x reference. d_gg: (G, G) found x found. d_rr: (R, R).
    Returns:
        ``{"mmd", "cov", "nna"}``; ties in the nearest neighbour go to the lower index, the
        reference set's shapes after the found set's (as ``numpy.argmin``).
    """
    d_gr, d_gg, d_rr = (np.asarray(x, dtype=np.float64) for x in (d_gr, d_gg, d_rr))
    g, r = d_gr.shape
    if g == 0 or r == 0 or d_gg.shape != (g, g) or d_rr.shape != (r, r):
        raise ConfigError(f"set realism needs non-empty sets and matching matrices (got {d_gr.shape}, "
                          f"{d_gg.shape}, {d_rr.shape})")
    mmd = float(d_gr.min(axis=0).mean())
    cov = float(len(np.unique(d_gr.argmin(axis=1))) / r)
    full = np.block([[d_gg, d_gr], [d_gr.T, d_rr]])
    np.fill_diagonal(full, np.inf)
    nn = full.argmin(axis=1)
    own = np.r_[np.zeros(g, bool), np.ones(r, bool)]
    nna = float(np.mean(own[nn] == own))
    return {"mmd": mmd, "cov": cov, "nna": nna}


def set_jsd_distance(found: Sequence[np.ndarray], reference_histogram: np.ndarray) -> float:
    """Jensen-Shannon distance (sqrt of the divergence in nats; the Adv3D paper's "JSD") between
    the BEV histogram of all found shapes' points and the reference histogram."""
    hist = sum(bev_histogram(p) for p in found)
    return jsd(hist, reference_histogram)


def set_realism(found: Sequence[np.ndarray], reference: Sequence[np.ndarray],
                reference_histogram: np.ndarray | None = None) -> dict:
    """Set-level realism of found shapes' point samples against reference point samples.

    Args:
        found: G arrays (n, 3) of surface points, metres, vehicle frame, footprint-centred
            (``realism.sample_surface`` + ``footprint_centred``; seed 0, 1000 points as the
            reference's).
        reference: R arrays (m, 3) likewise (the library's CAD models: ``RealismReference.points``).
        reference_histogram: BEV histogram of the reference (``RealismReference.histogram``) for
            the set JSD; omitted: the reference points' own.
    Returns:
        JSON-able ``{"mmd_cd_m2", "cov_cd", "nna_cd", "jsd_distance", "n_found", "n_reference"}``.
    """
    if len(found) == 0 or len(reference) < 2:
        raise ConfigError(f"set realism needs at least one found shape and two reference shapes "
                          f"(got {len(found)} and {len(reference)})")
    d_gr = chamfer_matrix(found, reference)
    d_gg = chamfer_matrix(found, found)
    d_rr = chamfer_matrix(reference, reference)
    m = mmd_cov_1nna(d_gr, d_gg, d_rr)
    hist = reference_histogram if reference_histogram is not None else sum(bev_histogram(p) for p in reference)
    return {"mmd_cd_m2": m["mmd"], "cov_cd": m["cov"], "nna_cd": m["nna"],
            "jsd_distance": set_jsd_distance(found, hist), "n_found": len(found), "n_reference": len(reference)}


def meshes_set_realism(meshes: Sequence[tuple[np.ndarray, np.ndarray]], reference) -> dict:
    """``set_realism`` of metric meshes [(vertices, faces)] against a ``RealismReference``
    (its CAD models' stored 1000-point samples and histogram); each mesh sampled as the
    per-shape report samples it (1000 points, seed 0, footprint-centred)."""
    from .realism import N_POINTS, footprint_centred, sample_surface

    pts = [footprint_centred(sample_surface(v, f, N_POINTS, 0), v) for v, f in meshes]
    return set_realism(pts, list(np.asarray(reference.points, dtype=np.float64)), reference.histogram)
