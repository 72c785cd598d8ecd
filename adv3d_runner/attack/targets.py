"""Which actors an attack reshapes, and how a query's unit vectors become their shapes.

The paper (section 4.2, "multiple actors") attacks the m closest actors *in front of* the ego
at the start of the episode; each gets its own 5-D unit vector (3 PCA latents, width and
length scale), so a query for m actors is a vector of D = 5 m entries in [0, 1].

The ground-truth box follows the new shape: its length, width and height are the decoded
mesh's extents, so detection IoU, prediction matching and reactive traffic see the shape the
LiDAR sees.
"""
from __future__ import annotations

import numpy as np

from ..errors import ConfigError, EmptySurfaceError
from ..sim.episode import ShapeOverride


def select_targets(scene, m: int = 1, start_frame: int = 0, max_distance: float = 80.0, rank: int = 0) -> list[int]:
    """Ids of the ``m`` actors closest to the ego (centre distance) among those in front of it
    (positive longitudinal offset in the ego frame) at ``start_frame``, nearest first, after
    skipping the ``rank`` closest (``rank`` 1, ``m`` 1: the second closest alone).

    Raises:
        ConfigError: m < 1, rank < 0, or fewer than ``rank + 1`` actors in front within
            ``max_distance`` m.
    """
    if int(m) < 1:
        raise ConfigError(f"--actors must be >= 1, got {m}")
    if int(rank) < 0:
        raise ConfigError(f"--target-rank must be >= 0, got {rank}")
    ego = scene.ego_poses()[start_frame]
    c, s = np.cos(ego[2]), np.sin(ego[2])
    cand = []
    for actor in scene.actors:
        p = scene.actor_poses(actor.id)[start_frame]
        if not np.all(np.isfinite(p)):
            continue
        dx, dy = p[0] - ego[0], p[1] - ego[1]
        lon = c * dx + s * dy
        dist = float(np.hypot(dx, dy))
        if lon > 0 and dist <= max_distance:
            cand.append((dist, actor.id))
    if not cand:
        raise ConfigError(f"scene {scene.id}: no actor in front of the ego within {max_distance:g} m at frame {start_frame}")
    cand.sort()
    if len(cand) <= int(rank):
        raise ConfigError(f"scene {scene.id}: {len(cand)} actor(s) in front of the ego within {max_distance:g} m at "
                          f"frame {start_frame}, none of rank {int(rank)} (--target-rank counts from 0)")
    return [int(a) for _, a in cand[int(rank): int(rank) + int(m)]]


def split_query(u: np.ndarray, n_actors: int, per_actor: int = 5) -> np.ndarray:
    """(n_actors * per_actor,) query -> (n_actors, per_actor) unit vectors."""
    u = np.asarray(u, dtype=np.float64).reshape(-1)
    if len(u) != n_actors * per_actor:
        raise ConfigError(f"query has {len(u)} entries, expected {n_actors} x {per_actor}")
    return u.reshape(n_actors, per_actor)


def mesh_dimensions(vertices: np.ndarray) -> np.ndarray:
    """(3,) L, W, H (m): the extents of a mesh in its local frame (x front, y left, z up)."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0:
        raise EmptySurfaceError("decoded mesh has no vertices")
    return v.max(axis=0) - v.min(axis=0)


def decode_query(space, u: np.ndarray, actor_ids: list[int]) -> tuple[dict[int, ShapeOverride], dict]:
    """Decode a query into episode overrides.

    Args:
        space: a :class:`~adv3d_runner.shapes.shape_space.ShapeSpace`.
        u: (m * (K + 2),) unit vector(s). actor_ids: the m target ids.
    Returns:
        overrides {actor id: :class:`~adv3d_runner.sim.episode.ShapeOverride`} for
        ``run_episode``, and info {"latent": m x K, "scales": m x 2, "dimensions": m x 3}.
    Raises:
        EmptySurfaceError: some latent decodes to no surface (the query is invalid).
    """
    U = split_query(u, len(actor_ids), space.dim)
    overrides, latents, scales, dims = {}, [], [], []
    for aid, ui in zip(actor_ids, U):
        z, sc = space.unit_to_latent(ui)
        v, f = space.decode_latent(z, sc)
        if len(f) == 0:
            raise EmptySurfaceError(f"actor {aid}: latent decodes to an empty mesh")
        d = mesh_dimensions(v)
        if np.any(d <= 1e-3):
            raise EmptySurfaceError(f"actor {aid}: decoded mesh is degenerate (extents {d.tolist()})")
        overrides[int(aid)] = ShapeOverride(v, f, d)
        latents.append([float(x) for x in z])
        scales.append([float(x) for x in sc])
        dims.append([float(x) for x in d])
    return overrides, {"latent": latents, "scales": scales, "dimensions": dims}
