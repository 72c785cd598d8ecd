"""The typed configuration of an attack: :class:`AttackConfig` (the whole run, written to
``run.json``) and :class:`QuerySettings` (the part a worker needs to evaluate a query).

``run.json`` holds the :class:`AttackConfig` fields flat, in field order, exactly as the CLI
options (docs/formats.md, "Run bundle"); :meth:`AttackConfig.run_json` writes that mapping and
:meth:`AttackConfig.from_run_json` reads it back. A resumed run compares the stored mapping with
the new one key by key (``attack.journal.Journal.start``).

The shape space of a run is loaded in one place, :meth:`QuerySettings.load_shape_space` (once
per process and file).

The shape model and realism knobs (docs/realism.md: ``shape_model``, ``vd_bound``, ``vd_lattice``,
``max_mahalanobis``, ``class_scales``, ``realism_weight``) came after run.json version 1; they are
written only when set (``vd_*`` with ``shape_model`` ``vd``), so a run that uses none of them
writes the run.json it always wrote, and older runs resume and compare equal.

The experiment protocol (docs/results.md) added two: ``pred_reduction`` (how the objective's prediction term reduces over the H
waypoints; default ``"sum"``, paper Eq. 5 as written) is written unless it is ``"mean"``, the
form every older run used, which a run.json without the key reads as; ``scene_seeds`` (derive
each scene's search seed and LiDAR-noise seed from ``seed`` and the scene's content,
:func:`scene_seed`) is written when true; ``target_rank`` (attack the ``actors`` actors after
the ``target_rank`` closest in front: the paper's Table 2 attacks each of the 3 closest alone) is
written when not 0.

``region`` (``paper``: the paper's latent box; ``realistic``: where the calibrated realism
report passes, :mod:`.realism_constraints`) is written when it is not ``paper``, the region of
every run before the key, which a run.json without it reads as.
"""
from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..argtypes import SEED_MAX
from ..errors import ConfigError
from ..validate import Node
from .objective import DEFAULT_PRED_REDUCTION, LEGACY_PRED_REDUCTION, PRED_REDUCTIONS, ObjectiveWeights, parse_objective
from .names import MAX_MAHALANOBIS, MAX_REALISM_WEIGHT, MODES, SHAPE_MODELS  # noqa: F401  (re-exported)
from .vertex_deform import DEFAULT_LATTICE, MAX_VD_BOUND, check_lattice

#: Knobs added after run.json version 1, with the value that leaves them out of run.json.
_OPTIONAL_KEYS = {"shape_model": "latent", "max_mahalanobis": None, "class_scales": False, "realism_weight": 0.0,
                  "pred_reduction": LEGACY_PRED_REDUCTION, "scene_seeds": False, "target_rank": 0,
                  "region": "paper"}
_VD_KEYS = ("vd_bound", "vd_lattice")
#: Search regions of the latent shape model: ``paper`` (the paper's box: the latents' min/max,
#: scales 0.8-1.3) or ``realistic`` (where the realism report passes; realism_constraints.py).
REGIONS = ("paper", "realistic")
AUTONOMY = ("A", "oracle", "B", "A-fast")
#: Bounds of the options (the CLI's argument types use the same ones).
MAX_ACTORS = 64
MAX_SECONDS = 3600.0
MAX_BUDGET = 1_000_000


@dataclass(frozen=True)
class QuerySettings:
    """What determines the score of one query on a scene, besides its shape: the stack, the
    targets, the objective and the episode (length, seed, reactive actors), and the shape space.

    Hashable: workers key their per-scene contexts on ``(scene, settings)``.
    """

    autonomy: str = "A"
    actors: int = 1
    objective: str = "M0"
    seconds: float = 5.0
    seed: int = 0
    reactive: bool = False
    shape_space: str | None = None
    shape_model: str = "latent"
    vd_bound: float = 0.5
    vd_lattice: tuple[int, int, int] = DEFAULT_LATTICE
    max_mahalanobis: float | None = None
    class_scales: bool = False
    realism_weight: float = 0.0
    library: str | None = None
    pred_reduction: str = DEFAULT_PRED_REDUCTION
    scene_seeds: bool = False
    target_rank: int = 0
    region: str = "paper"
    #: how, not what: reuse the static LiDAR hits between the queries of a scene
    #: (``sensors.incremental``); the results are identical either way.
    incremental: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "vd_lattice", check_lattice(self.vd_lattice))  # hashable tuple

    @property
    def weights(self) -> ObjectiveWeights:
        """The objective's weights (``objective`` parsed with the stack's presets) and form
        (``pred_reduction``)."""
        return replace(parse_objective(self.objective, self.autonomy), pred_reduction=self.pred_reduction)

    def episode_seed(self, scene_digest: str) -> int:
        """The seed of the search's episodes on a scene (the LiDAR noise): ``seed``, or with
        ``scene_seeds`` one derived from it and the scene's content (:func:`scene_seed`)."""
        return scene_seed(self.seed, scene_digest, "noise") if self.scene_seeds else int(self.seed)

    @property
    def shape_space_path(self) -> Path:
        """``shape_space``, or the shipped shape space when None."""
        from ..shapes.shape_space import DEFAULT_SHAPE_SPACE

        return Path(self.shape_space) if self.shape_space else DEFAULT_SHAPE_SPACE

    def load_shape_space(self):
        """The run's :class:`~adv3d_runner.shapes.shape_space.ShapeSpace`, loaded once per process
        (and again only when the file changes)."""
        path = self.shape_space_path
        try:
            st = path.stat()
            stamp = (st.st_mtime_ns, st.st_size)
        except OSError:
            stamp = None  # missing: ShapeSpace.load says so
        return _load_shape_space(str(path), stamp)

    def load_library(self):
        """The vehicle library the benign actors take their meshes from: ``library`` (a
        library.json, or ``"none"`` for boxes), or the bundled one when None (None when the
        bundled one is not there). Loaded once per process and path."""
        return _load_library(self.library)


def scene_seed(seed: int, scene_digest: str, stream: str) -> int:
    """A seed in [0, 2^32) for one scene and one use, derived from the run's ``seed``, the
    scene's content id (``scene_digest``, ``sha256:...``) and a stream name (``"search"``: the
    searcher's draws; ``"noise"``: the LiDAR noise of the search's episodes; the protocol's
    held-out evaluation seeds use their own streams). sha256 of ``"seed|digest|stream"``, first 4
    bytes big-endian: the same inputs give the same seed on every machine, and different scenes
    or streams give unrelated seeds, so searches differ per scene and the search's noise is not
    an evaluation's."""
    import hashlib

    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) <= SEED_MAX:
        raise ConfigError(f"seed must be an integer in [0, {SEED_MAX}], got {seed!r}")
    text = f"{int(seed)}|{scene_digest}|{stream}".encode("utf-8")
    return int.from_bytes(hashlib.sha256(text).digest()[:4], "big")


@functools.lru_cache(maxsize=4)
def _load_library(arg: str | None):
    if arg is None:
        from ..sim.episode import default_library

        return default_library()
    from ..shapes.library import resolve_library

    return resolve_library(arg)


def library_fingerprint_of(arg: str | None) -> str | None:
    """The ``library_fingerprint`` of the library a ``--library`` value names (None: boxes)."""
    from ..shapes.library import library_fingerprint

    library = _load_library(arg)
    return None if library is None else library_fingerprint(library)


@functools.lru_cache(maxsize=4)
def _load_shape_space(path: str, stamp: tuple[int, int] | None):
    from ..shapes.shape_space import ShapeSpace

    return ShapeSpace.load(path)


@dataclass(frozen=True)
class AttackConfig:
    """Everything that determines an attack's results (``run.json``; see the CLI options).

    ``scenes`` is kept as a tuple (a list is accepted). ``batch`` is the number of queries a
    search asks at once (``--batch``; independent of the number of workers, which does not
    change results; a resume must use the stored one).
    """

    scenes: tuple[str, ...]
    algo: str = "bo"
    budget: int = 100
    actors: int = 1
    mode: str = "closed"
    seconds: float = 5.0
    seed: int = 0
    objective: str = "M0"
    autonomy: str = "A"
    reactive: bool = False
    batch: int = 1
    n_initial: int = 11
    shape_space: str | None = None
    shape_model: str = "latent"
    vd_bound: float = 0.5
    vd_lattice: tuple[int, int, int] = DEFAULT_LATTICE
    max_mahalanobis: float | None = None
    class_scales: bool = False
    realism_weight: float = 0.0
    library: str | None = None
    pred_reduction: str = DEFAULT_PRED_REDUCTION
    scene_seeds: bool = False
    target_rank: int = 0
    region: str = "paper"

    def __post_init__(self) -> None:
        """Every field typed and in range (``ConfigError`` naming the option): a config built
        in code or read from run.json is checked like the command line."""
        from .search import ALGORITHMS

        object.__setattr__(self, "scenes", tuple(self.scenes))
        if not self.scenes or not all(isinstance(s, str) and s for s in self.scenes):
            raise ConfigError(f"scenes must be a non-empty list of scene files, got {list(self.scenes)!r}")
        if self.algo not in ALGORITHMS:
            raise ConfigError(f"--algo must be one of {', '.join(ALGORITHMS)}, got {self.algo!r}")
        object.__setattr__(self, "vd_lattice", check_lattice(self.vd_lattice))
        self._check_shape_options()
        if self.mode not in MODES:
            raise ConfigError(f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        from ..autonomy.names import check_spec

        try:
            check_spec(self.autonomy)
        except ConfigError as exc:
            raise ConfigError(f"--autonomy: {exc}") from None
        for name, lo, hi in (("budget", 1, MAX_BUDGET), ("actors", 1, MAX_ACTORS), ("seed", 0, SEED_MAX),
                             ("batch", 1, 4096), ("n_initial", 1, MAX_BUDGET), ("target_rank", 0, MAX_ACTORS - 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                option = "--" + name.replace("_", "-")
                raise ConfigError(f"{option} must be an integer in [{lo}, {hi}], got {value!r}")
        if (isinstance(self.seconds, bool) or not isinstance(self.seconds, (int, float))
                or not math.isfinite(self.seconds) or not 0 < self.seconds <= MAX_SECONDS):
            raise ConfigError(f"--seconds must be a finite number in (0, {MAX_SECONDS:g}], got {self.seconds!r}")
        if not isinstance(self.reactive, bool):
            raise ConfigError(f"--reactive must be true or false, got {self.reactive!r}")
        if not isinstance(self.scene_seeds, bool):
            raise ConfigError(f"--scene-seeds must be true or false, got {self.scene_seeds!r}")
        if self.pred_reduction not in PRED_REDUCTIONS:
            raise ConfigError(f"--pred-reduction must be one of {', '.join(PRED_REDUCTIONS)}, "
                              f"got {self.pred_reduction!r}")
        if self.shape_space is not None and not (isinstance(self.shape_space, str) and self.shape_space):
            raise ConfigError(f"--shape-space must be a file name, got {self.shape_space!r}")
        if not isinstance(self.objective, str):
            raise ConfigError(f"--objective must be a string, got {self.objective!r}")
        parse_objective(self.objective, self.autonomy)  # validate early (B has its own presets)
        self._check_memory()

    def _check_memory(self) -> None:
        """The search's arrays within ``fileio.MEMORY_BUDGET`` (``search.check_search_memory``):
        exactly for vertex deformation, whose dimension the options give; for the latent model
        with one dimension per actor, a lower bound (the shape space gives K + 2), which catches a
        budget too large for the searcher's own matrices here; the run checks the exact one."""
        from .search import check_search_memory
        from .vertex_deform import lattice_dim

        if self.shape_model == "vd":
            per_actor = lattice_dim(self.vd_lattice)
            check_search_memory(self.algo, per_actor * self.actors, self.budget, self.n_initial, self.batch,
                                what=f"--vd-lattice {','.join(map(str, self.vd_lattice))} ({per_actor} dimensions "
                                     f"per actor, --actors {self.actors})")
        elif self.algo != "bruteforce":
            check_search_memory(self.algo, self.actors, self.budget, self.n_initial, self.batch,
                                what=f"--actors {self.actors}" if self.algo == "grid" else f"--budget {self.budget}")

    def _check_shape_options(self) -> None:
        if self.shape_model not in SHAPE_MODELS:
            raise ConfigError(f"--shape-model must be one of {', '.join(SHAPE_MODELS)}, got {self.shape_model!r}")
        if not (np.isfinite(self.realism_weight) and 0 <= self.realism_weight <= MAX_REALISM_WEIGHT):
            raise ConfigError(f"--realism-weight must be a number in [0, {MAX_REALISM_WEIGHT:g}], got {self.realism_weight}")
        if self.max_mahalanobis is not None and not (np.isfinite(self.max_mahalanobis)
                                                     and 0 < self.max_mahalanobis <= MAX_MAHALANOBIS):
            raise ConfigError(f"--max-mahalanobis must be a number in (0, {MAX_MAHALANOBIS:g}], got {self.max_mahalanobis}")
        if self.region not in REGIONS:
            raise ConfigError(f"--region must be one of {', '.join(REGIONS)}, got {self.region!r}")
        region = self.max_mahalanobis is not None or self.class_scales or self.region == "realistic"
        if self.shape_model == "vd":
            if not (np.isfinite(self.vd_bound) and 0 < self.vd_bound <= MAX_VD_BOUND):
                raise ConfigError(f"--vd-bound must be a number of metres in (0, {MAX_VD_BOUND:g}], got {self.vd_bound}")
            if self.algo in ("grid", "bruteforce"):
                raise ConfigError(f"--algo {self.algo} does not apply to vertex deformation (a grid of 3^D points "
                                  f"in D = 3 x lattice nodes, or the library's latents); use bo, random or blendsearch")
            if region:
                raise ConfigError("--max-mahalanobis, --class-scales and --region realistic restrict the latent "
                                  "shape space; they do not apply to --shape-model vd (use --region paper)")
        if region and self.algo == "bruteforce":
            raise ConfigError("bruteforce enumerates the library's own vehicles; --max-mahalanobis, "
                              "--class-scales and --region realistic do not apply (use --region paper)")

    @property
    def modes(self) -> list[str]:
        """The attack modes in the order they run."""
        return ["open", "closed"] if self.mode == "both" else [self.mode]

    @property
    def settings(self) -> QuerySettings:
        """The part of the config a worker needs (:class:`QuerySettings`)."""
        return QuerySettings(autonomy=self.autonomy, actors=self.actors, objective=self.objective,
                             seconds=self.seconds, seed=self.seed, reactive=self.reactive,
                             shape_space=self.shape_space, shape_model=self.shape_model, vd_bound=self.vd_bound,
                             vd_lattice=self.vd_lattice, max_mahalanobis=self.max_mahalanobis,
                             class_scales=self.class_scales, realism_weight=self.realism_weight,
                             library=self.library, pred_reduction=self.pred_reduction,
                             scene_seeds=self.scene_seeds, target_rank=self.target_rank, region=self.region)

    def search_seed(self, scene_digest: str) -> int:
        """The seed of the searcher on a scene: ``seed``, or with ``scene_seeds`` one derived
        from it and the scene's content (:func:`scene_seed`), so every scene gets its own
        sequence of queries."""
        return scene_seed(self.seed, scene_digest, "search") if self.scene_seeds else int(self.seed)

    def with_batch(self, batch: int) -> "AttackConfig":
        """The same config with another batch size (a resume keeps the first run's)."""
        return replace(self, batch=int(batch))

    def run_json(self) -> dict[str, Any]:
        """The fields as stored in ``run.json`` (field order, ``scenes`` as a list; the knobs added
        after version 1 only when set, ``vd_bound`` / ``vd_lattice`` only for ``vd``)."""
        doc = asdict(self)
        doc["scenes"] = list(self.scenes)
        doc["vd_lattice"] = list(self.vd_lattice)
        for key, default in _OPTIONAL_KEYS.items():
            if doc[key] == default:
                del doc[key]
        if self.shape_model != "vd":
            for key in _VD_KEYS:
                del doc[key]
        return doc

    @classmethod
    def from_run_json(cls, doc: Mapping[str, Any], path: str | Path | None = None) -> "AttackConfig":
        """The config stored in a ``run.json`` mapping (other keys, e.g. ``versions``, ignored).

        Raises:
            FileFormatError: naming ``path`` and the field, for a missing ``scenes`` or a
                value that is not a valid option.
        """
        node = Node(doc, "$", path)
        node.object("a JSON object")
        node["scenes"].items("a non-empty list of scene files", non_empty=True)
        kw = {f.name: doc[f.name] for f in fields(cls) if f.name in doc}
        kw.setdefault("pred_reduction", LEGACY_PRED_REDUCTION)  # every run before the key used the mean
        try:
            return cls(**kw)
        except ConfigError as exc:  # messages start with the option: "--budget must be ..."
            name = str(exc).split(" ", 1)[0].lstrip("-").replace("-", "_")
            target = node.child(name, kw[name]) if name in kw else node
            target.fail("a valid attack option", str(exc))
