"""Realism-aware attacks (docs/realism.md): a search region restricted to where real vehicles
lie, a realism penalty in the objective, and the named presets of both.

The searchers work in the unit cube; these maps send the cube into the restricted region, so
every searcher (BO, random, grid, BlendSearch) searches it unchanged:

* **Mahalanobis region** (``--max-mahalanobis R``): the latent part of a query is mapped
  radially onto the intersection of the Mahalanobis ball of radius R around the library mean
  (the realism module's shrunk covariance) with the shape space's latent box
  (:class:`LatentRegion`). Every latent of the region, and only those, is reached.
* **Class-plausible scales** (``--class-scales``): the width and length scales are mapped into
  the scales that keep the decoded shape's width and length inside the real range of the
  attacked actor's class (``vehicle_classes.DIMENSION_RANGES``), intersected with the shape
  space's scale range (:func:`plausible_scale_range`).
* **Realism penalty** (``--realism-weight W``): the objective becomes ``C - W * P`` with
  ``P = sum over attacked actors of max(0, JSD - JSD_limit)``, the JSD excess over the library's
  leave-one-out maximum (:func:`realism_penalty`); ``P`` is journalled unweighted as the
  ``realism_penalty`` component.

* **The realistic region** (``--region realistic``, the command's default for latent shapes):
  latents in the Mahalanobis ball of the realism report's own limit (the calibrated
  ``RealismReference.mahalanobis_limit``; ``--max-mahalanobis`` overrides the radius),
  class-plausible scales, and every query's shapes checked with the whole realism report
  (``shapes.realism``): a shape that fails it is moved toward the cube's centre (the library's
  mean latent at mid-range scales) to the first point that passes
  (``shape_models.ActorShapes.realistic_unit``); when none does, the query is ``invalid``
  (:class:`UnrealisticShapeError`), never simulated. So every shape a search simulates and keeps
  passes the report, whatever its limits are set to.

Definitions, costs and the sweep that chose the preset: docs/realism.md.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError, InvalidQueryError
from ..shapes.realism import regularised_covariance
from .names import PRESETS  # noqa: F401  (named settings of the realism knobs; re-exported)


class UnrealisticShapeError(InvalidQueryError):
    """A query of the realistic region none of whose shapes toward the region's centre passes the
    realism report."""


def preset_knobs(name: str) -> dict[str, Any]:
    """The AttackConfig fields a preset sets.

    Raises:
        ConfigError: unknown preset.
    """
    if name not in PRESETS:
        raise ConfigError(f"--realism-preset must be one of {', '.join(PRESETS)}, got {name!r}")
    return dict(PRESETS[name])


# ----------------------------------------------------------------------------- latent region


@dataclass(frozen=True)
class LatentRegion:
    """The latents within Mahalanobis distance ``radius`` of the library mean, inside the box.

    Attributes:
        mean: (K,) mean of the library latents.
        chol: (K, K) lower Cholesky factor of the shrunk covariance S (``realism.regularised_covariance``),
            so ``d = chol @ x`` has Mahalanobis length ``|x|``.
        radius: R (standard deviations, unitless).
        lo, hi: (K,) the shape space's latent box.
    """

    mean: np.ndarray
    chol: np.ndarray
    radius: float
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def from_space(cls, space, radius: float) -> "LatentRegion":
        """The region of ``space`` (its library latents and latent box) for radius R > 0."""
        if not np.isfinite(radius) or radius <= 0:
            raise ConfigError(f"--max-mahalanobis must be a finite number > 0, got {radius}")
        latents = np.asarray(space.latents, dtype=np.float64)
        chol = np.linalg.cholesky(regularised_covariance(latents))
        return cls(latents.mean(axis=0), chol, float(radius), np.asarray(space.latent_min, dtype=np.float64),
                   np.asarray(space.latent_max, dtype=np.float64))

    def to_latent(self, u: np.ndarray) -> np.ndarray:
        """(K,) unit vector -> (K,) latent in the region.

        Radial map: ``v = 2 u - 1`` in [-1, 1]^K; its direction (Euclidean) becomes the direction
        ``d = chol @ v / |v|`` of unit Mahalanobis length, its l-infinity norm ``t = max |v_i|``
        the fraction of the way from the mean to the region's boundary along ``d``, which lies at
        ``min(R, box limit along d)``. The cube's centre is the mean, its surface the boundary;
        the map is continuous and reaches every point of the region (a star-shaped set around
        the mean). The Mahalanobis distance of the result is ``t * min(R, box limit) <= R``.
        """
        v = 2.0 * np.asarray(u, dtype=np.float64).reshape(-1) - 1.0
        t = float(np.max(np.abs(v))) if len(v) else 0.0
        if t == 0.0:
            return self.mean.copy()
        d = self.chol @ (v / np.linalg.norm(v))
        with np.errstate(divide="ignore", invalid="ignore"):
            to_wall = np.where(d > 0, (self.hi - self.mean) / d, np.where(d < 0, (self.lo - self.mean) / d, np.inf))
        s_max = min(self.radius, float(np.min(to_wall)))
        return np.clip(self.mean + t * max(s_max, 0.0) * d, self.lo, self.hi)


# ----------------------------------------------------------------------------- class scales


def plausible_scale_range(base: float, real: Sequence[float], scale_range: Sequence[float]) -> tuple[float, float]:
    """Scales ``s`` within ``scale_range`` for which ``s * base`` lies in the real range.

    Args:
        base: the decoded extent at scale 1 (metres, > 0).
        real: (low, high) real extents of the class (metres).
        scale_range: (low, high) the shape space's scales.
    Returns:
        (low, high) with low <= high. When no scale of ``scale_range`` reaches the real range,
        the one that comes closest, as (s, s).
    """
    s_lo, s_hi = float(scale_range[0]), float(scale_range[1])
    lo, hi = max(s_lo, real[0] / base), min(s_hi, real[1] / base)
    if lo <= hi:
        return lo, hi
    s = s_hi if real[0] / base > s_hi else s_lo
    return s, s


# ----------------------------------------------------------------------------- penalty


def realism_penalty(figures: Sequence[dict], jsd_limit: float) -> float:
    """``sum over actors of max(0, JSD - jsd_limit)``: the JSD excess over the library's own
    leave-one-out maximum (0 for shapes as realistic as the library's least typical member).

    Args:
        figures: per attacked actor, a dict with ``jsd`` (``realism.quick_measures``).
        jsd_limit: ``RealismReference.jsd_limit``.
    """
    return float(sum(max(0.0, float(f["jsd"]) - float(jsd_limit)) for f in figures))
