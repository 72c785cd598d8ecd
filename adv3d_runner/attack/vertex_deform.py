"""The paper's vertex-deformation (VD) baseline (section 4.3, "Latent Asset Representation";
supplementary Table 8): per-vertex displacements of a template mesh under an l-infinity bound,
searched by the same black-box searchers as the latent attack.

The paper deforms a decoded mean shape of 252 vertices (756 free coordinates) and, in its
appendix, a 100-triangle mesh (52 vertices, 156 coordinates) "which has a lower dimension thus
can be optimized with BO". We keep the template's full mesh and move it with a **control
lattice** (free-form deformation, Sederberg and Parry 1986): ``nx x ny x nz`` nodes spanning the
template's bounding box, each with a 3-D displacement; every vertex moves by the trilinear
interpolation of the displacements of its cell's 8 nodes. The default 6 x 3 x 3 lattice has 54
nodes, 162 coordinates: the appendix's dimension, while a zero displacement leaves the template
exactly as it is (the appendix's coarse mesh changes the shape before any attack).

Bound: a query's unit vector ``u`` maps to node displacements ``bound * (2 u - 1)`` (the cube's
centre is the template). Trilinear weights are non-negative and sum to 1, so every vertex's
displacement is a convex combination of node displacements: its l-infinity norm is at most the
bound, and vertices at nodes reach it. After the deformation the mesh is put back in the vehicle
frame (footprint centre at the origin, lowest point on the ground): a rigid shift, no change of
shape.

Template: the attacked actor's own mesh, i.e. the library vehicle the scene gives it (class and
closest dimensions, ``scene.actors.assign_assets``) scaled to its box; at zero displacement the
attack sees the original scene.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import ConfigError
from .names import MAX_VD_BOUND  # noqa: F401  (largest bound accepted, metres; re-exported)

#: The paper's l-infinity bounds (metres).
VD_BOUNDS = (0.1, 0.2, 0.5, 1.0)
#: Default control lattice (nodes along length, width, height): 54 nodes = 162 coordinates.
DEFAULT_LATTICE = (6, 3, 3)


def check_lattice(lattice: Sequence[int]) -> tuple[int, int, int]:
    """The lattice as a tuple of 3 ints >= 2.

    Raises:
        ConfigError: wrong length or a count < 2.
    """
    try:
        t = tuple(int(n) for n in lattice)
    except (TypeError, ValueError):
        raise ConfigError(f"--vd-lattice must be three integers NX,NY,NZ, got {lattice!r}") from None
    if len(t) != 3 or min(t) < 2 or any(int(n) != float(n) for n in lattice):
        raise ConfigError(f"--vd-lattice must be three integers >= 2, got {list(lattice)}")
    return t  # type: ignore[return-value]


def lattice_dim(lattice: Sequence[int]) -> int:
    """Search dimension of one actor: 3 coordinates per lattice node."""
    nx, ny, nz = check_lattice(lattice)
    return 3 * nx * ny * nz


def lattice_weights(vertices: np.ndarray, lattice: Sequence[int], lo: np.ndarray,
                    hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear weights of each vertex on a regular lattice spanning the box ``[lo, hi]``.

    Args:
        vertices: (V, 3) metres. lattice: (nx, ny, nz) nodes per axis, each >= 2.
        lo, hi: (3,) the box corners (the lattice's first and last nodes).
    Returns:
        nodes (V, 8) int64 flat node indices (C order over (ix, iy, iz)) and weights (V, 8)
        float64, non-negative, summing to 1 per vertex.
    """
    n = np.asarray(check_lattice(lattice))
    v = np.asarray(vertices, dtype=np.float64)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    t = np.clip((v - lo) / span, 0.0, 1.0) * (n - 1)
    cell = np.minimum(np.floor(t).astype(np.int64), n - 2)
    frac = t - cell
    nodes = np.empty((len(v), 8), dtype=np.int64)
    weights = np.empty((len(v), 8), dtype=np.float64)
    for c, (a, b, e) in enumerate(np.ndindex(2, 2, 2)):
        idx = cell + np.array([a, b, e])
        nodes[:, c] = (idx[:, 0] * n[1] + idx[:, 1]) * n[2] + idx[:, 2]
        weights[:, c] = ((frac[:, 0] if a else 1 - frac[:, 0]) * (frac[:, 1] if b else 1 - frac[:, 1])
                         * (frac[:, 2] if e else 1 - frac[:, 2]))
    return nodes, weights


def to_vehicle_frame(vertices: np.ndarray) -> np.ndarray:
    """Shift a mesh so its footprint (x/y bounding box) centre is at the origin and its lowest
    point at z = 0 (the project's vehicle frame)."""
    v = np.array(vertices, dtype=np.float64)
    mn, mx = v.min(axis=0), v.max(axis=0)
    v[:, 0] -= 0.5 * (mn[0] + mx[0])
    v[:, 1] -= 0.5 * (mn[1] + mx[1])
    v[:, 2] -= mn[2]
    return v


@dataclass
class VertexDeformation:
    """A template mesh deformed through a control lattice under an l-infinity bound.

    Attributes:
        vertices: (V, 3) template, metres, vehicle frame. faces: (F, 3) int64.
        bound: l-infinity bound of every vertex displacement, metres (> 0).
        lattice: (nx, ny, nz) control nodes.
    """

    vertices: np.ndarray
    faces: np.ndarray
    bound: float
    lattice: tuple[int, int, int] = DEFAULT_LATTICE
    _nodes: np.ndarray = field(init=False, repr=False)
    _weights: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.lattice = check_lattice(self.lattice)
        if not np.isfinite(self.bound) or not 0 < self.bound <= MAX_VD_BOUND:
            raise ConfigError(f"--vd-bound must be a number of metres in (0, {MAX_VD_BOUND:g}], got {self.bound}")
        if len(self.vertices) == 0 or len(self.faces) == 0:
            raise ConfigError("vertex deformation needs a template mesh with faces")
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        self._nodes, self._weights = lattice_weights(self.vertices, self.lattice, lo, hi)

    @property
    def dim(self) -> int:
        """Search dimension: 3 coordinates per lattice node."""
        return lattice_dim(self.lattice)

    def node_displacements(self, u: np.ndarray) -> np.ndarray:
        """(dim,) unit vector -> (nodes, 3) displacements ``bound * (2 u - 1)``, metres."""
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        if u.shape != (self.dim,):
            raise ConfigError(f"a vertex-deformation query has {self.dim} entries per actor, got {u.shape}")
        return self.bound * (2.0 * np.clip(u, 0.0, 1.0) - 1.0).reshape(-1, 3)

    def displacements(self, u: np.ndarray) -> np.ndarray:
        """(V, 3) per-vertex displacements of ``u`` (l-infinity norm <= bound), metres."""
        d = self.node_displacements(u)
        return np.einsum("vc,vcd->vd", self._weights, d[self._nodes])

    def deform(self, u: np.ndarray) -> np.ndarray:
        """(V, 3) deformed vertices in the vehicle frame (faces unchanged), metres."""
        return to_vehicle_frame(self.vertices + self.displacements(u))
