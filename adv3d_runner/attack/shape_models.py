"""How a query's unit vector becomes the attacked actors' shapes, and how realistic they are.

:class:`ActorShapes` is built once per scene workspace from the run's
:class:`~adv3d_runner.attack.config.QuerySettings`. Shape models (``SHAPE_MODELS``):

* ``latent`` (the paper's): each actor's K + 2 unit entries are a latent and two scales of the
  shape space. Optionally restricted to where real vehicles lie (``max_mahalanobis``,
  ``class_scales``; :mod:`.realism_constraints`). Without restrictions a query decodes exactly
  as :func:`.targets.decode_query` (same arrays).
* ``vd``: the paper's vertex-deformation baseline (:mod:`.vertex_deform`): the actor's own mesh
  deformed through a control lattice under an l-infinity bound.

Realism: :meth:`ActorShapes.figures` gives each decoded shape's cheap figures
(``shapes.realism.quick_measures``: JSD, nearest CAD model, Mahalanobis, dimensions against
the actor's class), which every journal line carries; :meth:`ActorShapes.full_reports` the
whole realism report, computed for best shapes only (docs/realism.md, "Per query and live").
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import ConfigError, EmptySurfaceError
from ..shapes import realism
from ..sim.episode import ShapeOverride
from ..vehicle_classes import DIMENSION_RANGES
from .realism_constraints import LatentRegion, plausible_scale_range
from .targets import mesh_dimensions, split_query
from .vertex_deform import VertexDeformation, lattice_dim, to_vehicle_frame

SHAPE_MODELS = ("latent", "vd")


def dim_per_actor(settings, space) -> int:
    """Search dimension of one attacked actor under ``settings`` (K + 2, or 3 per lattice node)."""
    return lattice_dim(settings.vd_lattice) if settings.shape_model == "vd" else space.dim


def actor_classes(scene, targets: list[int]) -> list[str | None]:
    """Per target, its class when the real-dimension table has it, else None."""
    by_id = {a.id: a for a in scene.actors}
    return [by_id[t].cls if t in by_id and by_id[t].cls in DIMENSION_RANGES else None for t in targets]


def own_meshes(scene, targets: list[int], library=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each target's mesh as the scene gives it (library asset by class and closest dimensions,
    scaled to the actor's box), in the vehicle frame.

    Raises:
        ConfigError: an actor without a library asset (an empty library).
    """
    from ..scene.actors import actor_mesh, assign_assets
    from ..sim.episode import default_library

    library = library if library is not None else default_library()
    by_id = {a.id: a for a in assign_assets(scene, library).actors}
    out = []
    for t in targets:
        actor = by_id[t]
        if actor.asset is None:
            raise ConfigError(f"actor {t} has no library mesh to deform")
        mesh = actor_mesh(library, actor.asset, actor.dimensions)
        out.append((to_vehicle_frame(np.asarray(mesh.vertices)), np.asarray(mesh.faces, dtype=np.int64)))
    return out


class ActorShapes:
    """The shapes of a scene's attacked actors under a run's settings (one per workspace).

    Args:
        settings: the run's ``QuerySettings`` (shape_model, vd_bound, vd_lattice,
            max_mahalanobis, class_scales).
        scene: the scene. targets: the attacked actor ids.
        space: the run's shape space (also the realism reference's asset set for ``vd``).
        library: the vehicle library for ``vd`` templates and the realism reference of a shape
            space without a known one (default: the bundled one).
    """

    def __init__(self, settings, scene, targets: list[int], space, library=None):
        self.settings = settings
        self.space = space
        self.library = library
        self.targets = list(targets)
        self.classes = actor_classes(scene, self.targets)
        self.region = None
        self.templates: list[VertexDeformation] = []
        self._reference = None
        self._projected: dict[tuple, tuple[np.ndarray, dict]] = {}
        #: the realistic region (``settings.region``): class scales, the report's Mahalanobis
        #: limit as radius, and every shape checked (:meth:`check_realistic`)
        self.realistic = getattr(settings, "region", "paper") == "realistic"
        self.class_scales = bool(settings.class_scales) or self.realistic
        if settings.shape_model == "vd":
            self.templates = [VertexDeformation(v, f, settings.vd_bound, settings.vd_lattice)
                              for v, f in own_meshes(scene, self.targets, library)]
        elif settings.max_mahalanobis is not None:
            self.region = LatentRegion.from_space(space, settings.max_mahalanobis)
        elif self.realistic:
            self.region = LatentRegion.from_space(space, self.reference.mahalanobis_limit)

    @property
    def per_actor(self) -> int:
        return dim_per_actor(self.settings, self.space)

    @property
    def reference(self) -> realism.RealismReference:
        """The realism reference of the run's shape space (loaded on first use)."""
        if self._reference is None:
            self._reference = realism.default_reference(self.space, self.library)
        return self._reference

    # ------------------------------------------------------------------ decoding
    def decode_actor(self, i: int, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                            np.ndarray | None]:
        """Target i's unit vector -> (vertices (V, 3) m, faces (F, 3), latent (K,) or None,
        scales (width, length) or None). In the realistic region the unit vector is first moved
        onto the region (:meth:`realistic_unit`).

        Raises:
            EmptySurfaceError: the latent has no surface.
            UnrealisticShapeError: realistic region, and no shape on the way to the centre passes.
        """
        if self.realistic:
            u = self.realistic_unit(i, u)[0]
        return self._decode_raw(i, u)

    #: fractions t of the way from the region's centre to the asked point tried, in order
    #: (:meth:`realistic_unit`)
    PROJECTION_STEPS = (1.0, 0.75, 0.5, 0.25, 0.0)

    def realistic_unit(self, i: int, u: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        """Target i's unit vector moved into the realistic region: the first point
        ``c + t (u - c)`` (c the cube's centre: the library's mean latent at mid-range scales;
        t in :data:`PROJECTION_STEPS`, from 1 = ``u`` itself) whose shape passes the realism
        report, with that report. Deterministic; remembered for the last few vectors (a query
        is decoded for its episode and reported for its realism).

        Raises:
            UnrealisticShapeError: no point of the way passes (the centre fails too).
        """
        from .realism_constraints import UnrealisticShapeError

        u = np.asarray(u, dtype=np.float64).reshape(-1)
        key = (i, u.tobytes())
        hit = self._projected.get(key)
        if hit is not None:
            return hit
        c = np.full_like(u, 0.5)
        flags: list[str] = []
        empty: EmptySurfaceError | None = None
        for t in self.PROJECTION_STEPS:
            cand = c + t * (u - c)
            try:
                rep = self._report_raw(i, cand)
            except EmptySurfaceError as exc:
                empty = exc
                continue
            if rep.get("realistic", not rep.get("flags")):
                rep = {**rep, "projection_t": float(t)}
                if len(self._projected) >= 16:
                    self._projected.pop(next(iter(self._projected)))
                self._projected[key] = (cand, rep)
                return cand, rep
            flags = flags or list(rep.get("flags") or [])
        if empty is not None and not flags:  # nothing decoded at all: that is the reason, not realism
            raise empty
        raise UnrealisticShapeError(f"actor {self.targets[i]}: no shape between the query and the realistic "
                                    f"region's centre passes the realism report (the query fails "
                                    f"{', '.join(flags) or 'it'})")

    def passes(self, u: np.ndarray) -> bool:
        """Whether every attacked actor's shape of ``u`` passes the realism report as it is
        (unmoved; the realistic prior of ``attack.failure_rate`` samples by this)."""
        U = split_query(u, len(self.targets), self.per_actor)
        for i, ui in enumerate(U):
            try:
                rep = self._report_raw(i, ui)
            except EmptySurfaceError:
                return False
            if not rep.get("realistic", not rep.get("flags")):
                return False
        return True

    def _decode_raw(self, i: int, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                          np.ndarray | None]:
        """:meth:`decode_actor` without moving ``u`` onto the realistic region."""
        if self.templates:
            t = self.templates[i]
            return t.deform(u), t.faces, None, None
        space = self.space
        if self.region is None and not self.class_scales:
            z, sc = space.unit_to_latent(u)  # the paper's box: exactly targets.decode_query
            v, f = space.decode_latent(z, sc)
            return v, f, z, sc
        u = space.check_unit(u)
        z = self.region.to_latent(u[:space.k]) if self.region is not None else space.unit_to_latent(u)[0]
        cls = self.classes[i]
        if not self.class_scales or cls is None:
            sc = space.unit_to_latent(u)[1]
            v, f = space.decode_latent(z, sc)
            return v, f, z, sc
        from ..shapes.decode import extract_surface

        v, f = extract_surface(space.decode_sdf(z), space.grid, (1.0, 1.0))
        base = mesh_dimensions(v)
        (l_real, w_real, _h) = DIMENSION_RANGES[cls]
        w_lo, w_hi = plausible_scale_range(base[1], w_real, space.scale_range)
        l_lo, l_hi = plausible_scale_range(base[0], l_real, space.scale_range)
        sc = np.array([w_lo + u[space.k] * (w_hi - w_lo), l_lo + u[space.k + 1] * (l_hi - l_lo)])
        v = v * np.array([sc[1], sc[0], 1.0])  # length scales x, width scales y (as extract_surface)
        return to_vehicle_frame(v), f, z, sc

    def decode_query(self, u: np.ndarray) -> tuple[dict[int, ShapeOverride], dict]:
        """A query -> (overrides {actor id: ShapeOverride}, info {"latent", "scales", "dimensions"}
        per actor; ``latent`` and ``scales`` None for vertex deformation).

        Raises:
            EmptySurfaceError: some shape has no surface or is degenerate (an invalid query).
        """
        U = split_query(u, len(self.targets), self.per_actor)
        overrides, latents, scales, dims = {}, [], [], []
        for i, (aid, ui) in enumerate(zip(self.targets, U)):
            v, f, z, sc = self.decode_actor(i, ui)
            if len(f) == 0:
                raise EmptySurfaceError(f"actor {aid}: latent decodes to an empty mesh")
            d = mesh_dimensions(v)
            if np.any(d <= 1e-3):
                raise EmptySurfaceError(f"actor {aid}: decoded mesh is degenerate (extents {d.tolist()})")
            overrides[int(aid)] = ShapeOverride(v, f, d)
            latents.append(None if z is None else [float(x) for x in z])
            scales.append(None if sc is None else [float(x) for x in sc])
            dims.append([float(x) for x in d])
        vd = bool(self.templates)
        return overrides, {"latent": None if vd else latents, "scales": None if vd else scales, "dimensions": dims}

    # ------------------------------------------------------------------ realism
    def figures(self, overrides: dict[int, ShapeOverride], info: dict) -> list[dict[str, Any]]:
        """Per target, the cheap realism figures the journal carries (``realism.quick_measures``
        against the actor's class), without ``dimensions_m`` (the line has ``dimensions``)."""
        out = []
        for i, aid in enumerate(self.targets):
            shape = overrides[int(aid)]
            z = None if info.get("latent") is None else info["latent"][i]
            fig = realism.quick_measures(shape.vertices, shape.faces, self.reference, latent=z,
                                         latents=self.space.latents, vehicle_class=self.classes[i])
            fig.pop("dimensions_m")
            out.append(fig)
        return out

    def full_reports(self, u: np.ndarray) -> list[dict[str, Any]]:
        """Per target, the whole realism report of the query's shape (best shapes; ~0.1 s each).

        Latent shapes: ``realism.latent_realism_report`` (JSD, nearest, Mahalanobis, artefacts,
        dimensions); in the realistic region the report of the shape the query was moved to
        (:meth:`realistic_unit`, with its ``projection_t``). Vertex-deformed meshes have no
        decoder field: the mesh measures only (``quick_measures`` + plausible classes), their
        limits and the largest vertex displacement actually applied (``max_displacement_m``).
        """
        U = split_query(u, len(self.targets), self.per_actor)
        if self.realistic:
            return [self.realistic_unit(i, ui)[1] for i, ui in enumerate(U)]
        return [self._report_raw(i, ui) for i, ui in enumerate(U)]

    def _report_raw(self, i: int, ui: np.ndarray) -> dict[str, Any]:
        """The realism report of target i's shape of ``ui`` (not moved onto any region)."""
        ref = self.reference
        v, f, z, sc = self._decode_raw(i, ui)
        if z is not None:
            return realism.latent_realism_report(self.space, z, sc, ref, vehicle_class=self.classes[i])
        rep = realism.quick_measures(v, f, ref, vehicle_class=self.classes[i])
        rep["plausible_classes"] = realism.plausible_classes(rep["dimensions_m"])
        lim = realism.LIMITS.resolve(ref, 0.0)  # the limits quick_measures checked (one place)
        rep["limits"] = {k: lim[k] for k in ("jsd", "nearest_chamfer_m", "dimension_excess")}
        rep["max_displacement_m"] = float(np.abs(self.templates[i].displacements(ui)).max())
        rep["realistic"] = not rep["flags"]
        return rep
