"""A cheap analytic stand-in for the episode evaluator, for tests (and ``bench/attack.py``) of
the attack machinery without the simulator.

Scenes named ``synthetic:NAME`` are analytic objectives over the unit cube (:data:`FUNCTIONS`),
with an invalid region: u[0] above :data:`INVALID` is an "empty surface" (status ``invalid``),
u[1] above it a "simulation error" (status ``error``). :class:`SyntheticEvaluator` implements
:class:`~adv3d_runner.attack.evaluator.QueryEvaluator`; pass the class as
``run_attack(..., evaluator=SyntheticEvaluator)``. It pickles by reference (this module), so
spawned worker processes, which inherit ``sys.path``, can run it too.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from adv3d_runner.attack.config import QuerySettings
from adv3d_runner.attack.evaluator import BestEvaluation, Query, QueryResult
from adv3d_runner.errors import ConfigError, EmptySurfaceError

PER_ACTOR = 5  # K + 2 for the paper's K = 3, as the shipped shape space
INVALID = 0.95


def peak(u: np.ndarray) -> float:
    """5-D: a smooth bowl with a narrow peak (height 2, width 0.05) at a fixed point."""
    c = np.array([0.73, 0.21, 0.58, 0.87, 0.34])
    d2 = float(np.sum((u[:5] - c) ** 2))
    return -d2 + 2.0 * np.exp(-d2 / (2 * 0.05**2))


def bowl(u: np.ndarray) -> float:
    """5-D: a smooth bowl around another point (a second scene for multi-scene runs)."""
    return -float(np.sum((u[:5] - 0.4) ** 2))


def ridge(u: np.ndarray) -> float:
    """5-D: a ridge along u[2] = u[3]."""
    return -abs(float(u[2] - u[3])) + 0.1 * float(u[4])


FUNCTIONS: dict[str, Callable[[np.ndarray], float]] = {"peak": peak, "bowl": bowl, "ridge": ridge}


class SyntheticEvaluator:
    """:class:`~adv3d_runner.attack.evaluator.QueryEvaluator` over ``synthetic:NAME`` scenes."""

    def __init__(self, settings: QuerySettings):
        self.settings = settings

    def scene_id(self, ref: str) -> str:
        return ref

    def scene_digest(self, ref: str) -> str:
        return ref  # an analytic scene is its name

    def targets(self, ref: str) -> tuple[list[int], int]:
        ids = list(range(self.settings.actors))
        return ids, PER_ACTOR * len(ids)

    def candidates(self, ref: str, targets: list[int]) -> np.ndarray:
        return np.random.default_rng(self.settings.seed).random((50, PER_ACTOR * len(targets)))

    def evaluate(self, query: Query) -> QueryResult:
        name = query.scene.split(":", 1)[1] if query.scene.startswith("synthetic:") else query.scene
        if name not in FUNCTIONS:
            raise ConfigError(f"unknown synthetic scene {name!r}; choose one of {', '.join(FUNCTIONS)}")
        u = query.unit
        if u[0] > INVALID:
            raise EmptySurfaceError("synthetic: no surface")
        if u[1] > INVALID:
            raise RuntimeError("synthetic: simulation error")
        v = FUNCTIONS[name](u)
        return QueryResult(cost=v, components={"synthetic": v}, metrics={})

    def versions(self) -> dict[str, Any]:
        return {}

    def evaluate_best(self, ref: str, targets: list[int], unit: np.ndarray, out: Path, *, original: bool,
                      metadata: dict[str, Any]) -> BestEvaluation | None:
        return None  # nothing to simulate, no files


class SyntheticWithBest(SyntheticEvaluator):
    """:class:`SyntheticEvaluator` whose best-shape evaluation writes a file and reports the
    original scene, like the episode evaluator; with ``ADV3D_TEST_PID_DIR`` set, every process
    that evaluates a query leaves a file named after its pid there (to see the workers used)."""

    def evaluate(self, query: Query) -> QueryResult:
        import os

        folder = os.environ.get("ADV3D_TEST_PID_DIR")
        if folder:
            Path(folder, str(os.getpid())).touch()
        return super().evaluate(query)

    def evaluate_best(self, ref: str, targets: list[int], unit: np.ndarray, out: Path, *, original: bool,
                      metadata: dict[str, Any]) -> BestEvaluation | None:
        name = ref.split(":", 1)[1]
        value = FUNCTIONS[name](np.asarray(unit))
        out.mkdir(parents=True, exist_ok=True)
        (out / "best.txt").write_text(f"{ref} {np.asarray(unit).tolist()} {metadata}\n")
        first = {"cost": FUNCTIONS[name](np.full(PER_ACTOR, 0.5))} if original else None
        return BestEvaluation(closed_loop={"cost": value}, original=first, meshes={}, replay="best.txt")


class SyntheticLogged(SyntheticEvaluator):
    """:class:`SyntheticEvaluator` taking 20-420 ms per query (by the query's own numbers, so
    workers finish out of order) and, with ``ADV3D_TEST_EVAL_LOG`` set, appending every query
    it evaluates (its unit vector, one JSON line) to that file, from whichever process runs it."""

    def evaluate(self, query: Query) -> QueryResult:
        import json
        import os
        import time

        time.sleep(0.02 + 0.4 * float(np.asarray(query.unit).reshape(-1)[2]))
        log = os.environ.get("ADV3D_TEST_EVAL_LOG")
        if log:
            fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            try:
                os.write(fd, (json.dumps(np.asarray(query.unit).reshape(-1).tolist()) + "\n").encode())
            finally:
                os.close(fd)
        return super().evaluate(query)
