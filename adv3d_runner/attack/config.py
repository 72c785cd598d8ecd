"""The typed configuration of an attack: :class:`AttackConfig` (the whole run, written to
``run.json``) and :class:`QuerySettings` (the part a worker needs to evaluate a query).

``run.json`` holds the :class:`AttackConfig` fields flat, in field order, exactly as the CLI
options (docs/formats.md, "Run bundle"); :meth:`AttackConfig.run_json` writes that mapping and
:meth:`AttackConfig.from_run_json` reads it back. A resumed run compares the stored mapping with
the new one key by key (``attack.journal.Journal.start``).

The shape space of a run is loaded in one place, :meth:`QuerySettings.load_shape_space` (once
per process and file).
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Mapping

from ..errors import ConfigError
from .objective import ObjectiveWeights, parse_objective

MODES = ("closed", "open", "both")


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
    #: how, not what: reuse the static LiDAR hits between the queries of a scene
    #: (``sensors.incremental``); the results are identical either way.
    incremental: bool = True

    @property
    def weights(self) -> ObjectiveWeights:
        """The objective's weights (``objective`` parsed)."""
        return parse_objective(self.objective)

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

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenes", tuple(self.scenes))
        if self.mode not in MODES:
            raise ConfigError(f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.budget < 1:
            raise ConfigError(f"--budget must be >= 1, got {self.budget}")
        if self.seconds <= 0:
            raise ConfigError(f"--seconds must be > 0, got {self.seconds}")
        if self.batch < 1:
            raise ConfigError(f"--batch must be >= 1, got {self.batch}")
        parse_objective(self.objective)  # validate early

    @property
    def modes(self) -> list[str]:
        """The attack modes in the order they run."""
        return ["open", "closed"] if self.mode == "both" else [self.mode]

    @property
    def settings(self) -> QuerySettings:
        """The part of the config a worker needs (:class:`QuerySettings`)."""
        return QuerySettings(autonomy=self.autonomy, actors=self.actors, objective=self.objective,
                             seconds=self.seconds, seed=self.seed, reactive=self.reactive,
                             shape_space=self.shape_space)

    def with_batch(self, batch: int) -> "AttackConfig":
        """The same config with another batch size (a resume keeps the first run's)."""
        return replace(self, batch=int(batch))

    def run_json(self) -> dict[str, Any]:
        """The fields as stored in ``run.json`` (field order, ``scenes`` as a list)."""
        doc = asdict(self)
        doc["scenes"] = list(self.scenes)
        return doc

    @classmethod
    def from_run_json(cls, doc: Mapping[str, Any]) -> "AttackConfig":
        """The config stored in a ``run.json`` mapping (other keys, e.g. ``versions``, ignored)."""
        names = [f.name for f in fields(cls)]
        missing = [n for n in ("scenes",) if n not in doc]
        if missing:
            raise ConfigError(f"run.json has no {', '.join(missing)}")
        return cls(**{n: doc[n] for n in names if n in doc})
