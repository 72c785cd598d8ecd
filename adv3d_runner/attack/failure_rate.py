"""How often a realistic shape makes the stack fail, beside the worst case the search found.

``adv3d rate RUN --samples N`` (and ``adv3d attack ... --failure-rate N``) draws N shapes per
attacked scene from the **realistic prior** and simulates each in closed loop with the run's
stack, episode length and objective:

* **Prior**: a unit vector uniform in the cube, mapped by the realistic region
  (``attack.realism_constraints``: latents radially into the Mahalanobis ball of the realism
  report's limit, class-plausible scales), kept only when every attacked actor's shape passes
  the realism report as drawn (``ActorShapes.passes``; no move toward the centre, which would put
  mass on the centre and the boundary). So the prior is the region's map of the uniform cube
  conditioned on the report passing; the rejected draws are counted (``rejected``) and never
  simulated. Draws are seeded (``default_rng([scene seed of stream "rate", i])``): the same run
  and N give the same shapes.
* **Episodes**: draw i runs on the scene's held-out evaluation seed i mod K
  (``protocol.evaluation_seeds``, K = ``--eval-seeds``), and the original scene on each of those
  K seeds, so ``low_progress`` compares with the original on the same seed.
* **Failures** per kind (:data:`~.avoidability.FAILURE_KINDS`, the avoidability rules) and
  ``any``; the rate k / n over the n accepted draws with a **Clopper-Pearson** interval
  (:func:`clopper_pearson`). Why that one: it is exact (its coverage is never below the
  nominal level, for every n and rate), and the rates of interest are near 0 with n of a few
  dozen, where the Wald interval collapses to a point at k = 0 and Wilson's, though usually
  closer to nominal on average, undercovers for some rates near 0; a safety claim ("at most x %
  of realistic shapes make it brake hard") wants the guaranteed side. The price is width: at
  k = 0 the upper bound is 1 - (alpha / 2)^(1/n), about 3.7 / n at 95 %, against Wilson's
  3.84 / (n + 3.84).

Rates are per scene and pooled over scenes (the share of (scene, shape) draws). The draws and
their episodes are kept in ``RUN/rate.json.gz`` (a :class:`~.protocol.HeldoutStore`, keys
``scene|rate<i>|seed``; a killed command resumes) and the result in ``RUN/failure_rate.json``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

from ..errors import ConfigError
from .avoidability import FAILURE_KINDS, episode_failures

FORMAT = "adv3d-failure-rate"
VERSION = 1
FILE = "failure_rate.json"
STORE = "rate.json.gz"
DEFAULT_CONFIDENCE = 0.95
#: Draws tried per accepted shape at most (a region where the report almost never passes ends
#: with fewer accepted draws, said in the result, rather than looping on).
MAX_DRAWS_PER_SAMPLE = 20


def clopper_pearson(k: int, n: int, confidence: float = DEFAULT_CONFIDENCE) -> tuple[float, float]:
    """Exact two-sided binomial interval of a rate k / n (Clopper and Pearson 1934): the beta
    quantiles ``Beta(alpha/2; k, n - k + 1)`` and ``Beta(1 - alpha/2; k + 1, n - k)``, with 0 at
    k = 0 and 1 at k = n. (nan, nan) for n = 0.

    Raises:
        ConfigError: k outside [0, n] or confidence outside (0, 1).
    """
    from scipy.stats import beta

    if not 0 < confidence < 1:
        raise ConfigError(f"--confidence must be in (0, 1), got {confidence}")
    if n == 0:
        return (math.nan, math.nan)
    if not 0 <= k <= n:
        raise ConfigError(f"a rate needs 0 <= k <= n, got k={k}, n={n}")
    a = 1.0 - confidence
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def rate_block(flags: Sequence[Mapping[str, bool | None]], confidence: float = DEFAULT_CONFIDENCE
               ) -> dict[str, dict[str, Any]]:
    """Per failure kind and ``any``: ``{"k", "n", "rate", "ci"}`` over the episodes' failures
    (:func:`~.avoidability.episode_failures`; an episode whose figure is missing is left out of
    that kind's n)."""
    out = {}
    for kind in (*FAILURE_KINDS, "any"):
        if kind == "any":
            vals = [any(bool(f.get(k)) for k in FAILURE_KINDS) for f in flags]
        else:
            vals = [bool(f[kind]) for f in flags if f.get(kind) is not None]
        k, n = sum(vals), len(vals)
        lo, hi = clopper_pearson(k, n, confidence)
        out[kind] = {"k": k, "n": n, "rate": k / n if n else None,
                     "ci": None if n == 0 else [round(lo, 6), round(hi, 6)]}
    return out


def sample_prior(ws, index: int, base_seed: int, dim: int) -> tuple[Any, int]:
    """Draw ``index`` of a scene: (the first unit vector of its seeded stream whose shapes pass
    the realism report, or None after :data:`MAX_DRAWS_PER_SAMPLE` tries; how many were
    rejected)."""
    import numpy as np

    rng = np.random.default_rng([int(base_seed), 7, int(index)])
    for tries in range(MAX_DRAWS_PER_SAMPLE):
        u = rng.random(dim)
        if ws.shapes.passes(u):
            return u, tries
    return None, MAX_DRAWS_PER_SAMPLE


def rate_evaluate(ref: str, settings, index: int, base_seed: int, seed: int) -> dict[str, Any]:
    """One draw of the prior on scene ``ref`` and its closed-loop episode on ``seed``:
    a held-out record (``protocol.heldout_evaluate``'s fields) plus ``rejected`` (draws thrown
    away before it) and ``accepted`` (False when none passed: no episode)."""
    from .evaluator import workspace_for
    from .protocol import _clean, heldout_evaluate

    ws = workspace_for(ref, settings)
    u, rejected = sample_prior(ws, index, base_seed, ws.shapes.per_actor * len(ws.targets))
    if u is None:
        return {"seed": int(seed), "cost": None, "components": {}, "metrics": {}, "accepted": False,
                "rejected": rejected}
    rec = heldout_evaluate(ref, settings, u, seed)
    return _clean({**rec, "accepted": True, "rejected": rejected, "drawn_unit": u.tolist()})


def run_failure_rate(run_dir: str | Path, *, samples: int, eval_seeds: int = 3,
                     confidence: float = DEFAULT_CONFIDENCE, on_done=None) -> dict[str, Any]:
    """Draw ``samples`` realistic shapes per attacked scene of the run, simulate them, and
    write and return the failure-rate document (``RUN/failure_rate.json``; module docstring).
    ``on_done(i, n)`` is called after each draw (progress).

    Raises:
        ConfigError: not a run folder, samples < 1, eval_seeds < 1, a vertex-deformation run.
    """
    from dataclasses import replace

    from ..fileio import write_json
    from .config import AttackConfig, scene_seed
    from .evaluator import EpisodeEvaluator
    from .journal import read_run
    from .protocol import HeldoutStore, evaluation_seeds, heldout_evaluate, heldout_key

    if samples < 1 or eval_seeds < 1:
        raise ConfigError(f"--samples and --eval-seeds must be at least 1, got {samples} and {eval_seeds}")
    root = Path(run_dir)
    run, _, summary = read_run(root)
    config = AttackConfig.from_run_json(run, root / "run.json")
    if config.shape_model != "latent":
        raise ConfigError(f"{root}: the realistic prior is over the latent shape space; this run deforms vertices")
    # the realistic prior whatever region the run searched; plain objective (no penalty)
    settings = replace(config.settings, region="realistic", max_mahalanobis=None, class_scales=False,
                       realism_weight=0.0)
    store = HeldoutStore(root / STORE)
    digest_of = EpisodeEvaluator(settings).scene_digest
    scenes: dict[str, Any] = {}
    pooled: list[dict] = []
    todo = [(sid, e) for sid, e in summary.get("scenes", {}).items() if "skipped" not in e and e.get("modes")]
    done, total = 0, len(todo) * samples
    for sid, entry in todo:
        ref = entry["ref"]
        digest = digest_of(ref)
        seeds = evaluation_seeds(config.seed, digest, eval_seeds)
        base = scene_seed(config.seed, digest, "rate")
        originals = {}
        for s in seeds:
            key = heldout_key(sid, "original", s)
            rec = store.get(key, None)
            if rec is None:
                rec = heldout_evaluate(ref, settings, None, s)
                store.put(key, None, rec)
            originals[s] = rec
        flags, rejected, unaccepted = [], 0, 0
        for i in range(samples):
            s = seeds[i % len(seeds)]
            key = heldout_key(sid, f"rate{i}", s)
            rec = store.evaluations.get(key)
            if rec is None:
                rec = rate_evaluate(ref, settings, i, base, s)
                store.put(key, None, rec)
            rejected += int(rec.get("rejected", 0))
            if rec.get("accepted"):
                flags.append(episode_failures(rec.get("metrics"), originals[s].get("metrics")))
            else:
                unaccepted += 1
            done += 1
            if on_done is not None:
                on_done(done, total)
        pooled += flags
        best = entry["modes"].get("closed") or next(iter(entry["modes"].values()))
        worst = (best.get("closed_loop_eval") or {})
        scenes[sid] = {"original_failures": {str(s): [k for k, v in episode_failures(
                           originals[s].get("metrics"), originals[s].get("metrics")).items() if v] for s in seeds},
                       "samples": samples, "accepted": len(flags), "rejected_draws": rejected,
                       "not_found": unaccepted, "seeds": seeds, "rates": rate_block(flags, confidence),
                       "worst_case": {"cost": best.get("best_cost"), "heldout": False,
                                      "failures": episode_failures(worst.get("metrics"),
                                                                   (entry.get("original") or {}).get("metrics"))}}
    doc = {"format": FORMAT, "version": VERSION, "stack": config.autonomy, "samples": samples,
           "eval_seeds": eval_seeds, "confidence": confidence, "interval": "clopper-pearson",
           "prior": "realistic region (Mahalanobis ball of the report's limit, class-plausible scales), uniform in "
                    "the cube, conditioned on passing the realism report",
           "scenes": scenes, "pooled": rate_block(pooled, confidence)}
    write_json(root / FILE, doc)
    return doc


def read_failure_rate(run_dir: str | Path) -> dict[str, Any] | None:
    """``RUN/failure_rate.json`` when there (format and version checked), else None."""
    from ..validate import read_optional_contract

    node = read_optional_contract(Path(run_dir) / FILE, FORMAT, (VERSION,))
    if node is None:
        return None
    node["scenes"].object("scene id -> the scene's failure rates")
    return node.value


def format_rate(block: Mapping[str, Any] | None) -> str:
    """``k/n (p %, CI lo-hi %)`` of one kind's rate block; ``-`` without draws."""
    if not block or not block.get("n"):
        return "-"
    lo, hi = block["ci"]
    return f"{block['k']}/{block['n']} ({100 * block['rate']:.0f} %, {100 * lo:.0f}-{100 * hi:.0f} %)"
