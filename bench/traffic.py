"""Generated traffic against recorded traffic (docs/scenes.md).

Statistics (``adv3d_runner.scene.traffic_stats``): speed, time headway and lane changes per 5 s
window of every vehicle, pooled over scenes, compared by the two-sample Kolmogorov-Smirnov
distance (0 = same distribution, 1 = disjoint). Samples:

* **real train / real benchmark**: the recorded scenes of ``scenes/real/`` (``split.json``
  parts), one file per distinct traffic (the rank-0 ego file of each set of variants: the
  ego and the actors together are the same vehicles in every variant); recorded frames only;
* **real fresh**: ``scenes/real-fresh/`` (recordings 10-18, docs/benchmark.md), one scene per
  recording (its egos share the traffic); never used by the fit;
* **default**: the 100 bundled benchmark scenes (``scenes/highway/``, the default profile);
* **us101**: scenes of the ``us101`` generator profile (``adv3d scenes generate --profile
  us101``), seeds 0.. of its benchmark split (never used by the fit).

``--fit`` searches the ``us101`` profile's parameters on the **train** part only (seeded random
search, then a local refinement around the best; each candidate is scored on a few scenes of the
profile's training-split seeds by the summed KS distances of the three statistics) and prints
the profile to paste into ``adv3d_runner/scene/generate.py``. Without ``--fit`` it compares
the profiles as they are in the code.

    .venv/bin/python bench/traffic.py [--fit] [--scenes 20]

Writes ``bench/results/traffic[.fit].json``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

FIT_SEED = 17
FIT_SCENES = 5                       # training-split scenes per candidate
FIT_RANDOM, FIT_LOCAL = 24, 12       # random candidates, then local perturbations of the best
# parameter: (low, high) of the search
SPACE = {"density": (25.0, 90.0), "v0_mean": (0.45, 1.0), "v0_std": (0.03, 0.25), "headway_scale": (0.35, 1.0),
         "headway_sigma": (0.0, 0.6), "s0": (1.0, 3.0), "a_thr": (0.0, 0.3), "politeness": (0.0, 0.5)}


def real_pool(part: str):
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.real import load_real_split
    from adv3d_runner.scene.traffic_stats import pool, traffic_samples

    scenes = [load_scene(p) for p in load_real_split().paths(part)]
    distinct = [s for s in scenes if "--ego-rank" not in s.source.details.get("ego_rule", "")]
    return pool(traffic_samples(s) for s in distinct), [s.id for s in distinct]


def fresh_pool():
    """Traffic of the fresh part: the first scene of each recording in its manifest (the other
    egos of a recording drive in the same traffic)."""
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.real import load_fresh_part
    from adv3d_runner.scene.traffic_stats import pool, traffic_samples

    fresh = load_fresh_part()
    first: dict = {}
    for row, path in zip(fresh.rows, fresh.paths()):
        first.setdefault(row["recording"], path)
    scenes = [load_scene(p) for p in first.values()]
    return pool(traffic_samples(s) for s in scenes), [s.id for s in scenes]


def generated_pool(profile, seeds, split: str):
    from adv3d_runner.scene.generate import generate_scene
    from adv3d_runner.scene.traffic_stats import pool, traffic_samples

    return pool(traffic_samples(generate_scene(int(s), split, profile=profile)) for s in seeds)


def make_profile(base, params: dict):
    """``base`` (a GeneratorProfile) with the searched parameters."""
    return replace(base, name="us101", density=float(params["density"]), v0_mean=float(params["v0_mean"]),
                   v0_std=float(params["v0_std"]), headway_scale=float(params["headway_scale"]),
                   headway_sigma=float(params["headway_sigma"]),
                   idm=replace(base.idm, s0=float(params["s0"])),
                   mobil=replace(base.mobil, a_thr=float(params["a_thr"]), politeness=float(params["politeness"])))


def fit(real_train) -> tuple[dict, list[dict]]:
    from adv3d_runner.scene.generate import PROFILES
    from adv3d_runner.scene.traffic_stats import compare

    base = PROFILES["us101"]
    rng = np.random.default_rng(FIT_SEED)
    seeds = range(100_000, 100_000 + FIT_SCENES)
    lo = np.array([v[0] for v in SPACE.values()])
    hi = np.array([v[1] for v in SPACE.values()])
    history = []

    def score(x: np.ndarray) -> float:
        params = dict(zip(SPACE, (float(v) for v in x)))
        t0 = time.process_time()
        ks = compare(generated_pool(make_profile(base, params), seeds, "train"), real_train)
        total = float(sum(ks.values()))
        history.append({"params": params, "ks": ks, "objective": total, "cpu_s": time.process_time() - t0})
        print(f"[{len(history)}] objective {total:.3f} ks {({k: round(v, 3) for k, v in ks.items()})} "
              f"{({k: round(v, 3) for k, v in params.items()})}", flush=True)
        return total

    xs = lo + rng.random((FIT_RANDOM, len(SPACE))) * (hi - lo)
    scores = [score(x) for x in xs]
    best = xs[int(np.argmin(scores))]
    best_score = min(scores)
    step = 0.15 * (hi - lo)
    for _ in range(FIT_LOCAL):
        x = np.clip(best + rng.normal(0.0, 1.0, len(SPACE)) * step, lo, hi)
        sc = score(x)
        if sc < best_score:
            best, best_score = x, sc
        else:
            step *= 0.9
    return dict(zip(SPACE, (float(v) for v in best))), history


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", action="store_true", help="search the us101 profile on the real train part")
    ap.add_argument("--scenes", type=int, default=20, help="us101 scenes for the comparison (benchmark-split seeds)")
    args = ap.parse_args()
    from adv3d_runner.fileio import write_json
    from adv3d_runner.scene import load_scene
    from adv3d_runner.scene.generate import PROFILES
    from adv3d_runner.scene.traffic_stats import STATS, compare, pool, summary, traffic_samples

    t0 = time.process_time()
    real = {}
    ids = {}
    for part in ("train", "benchmark"):
        real[part], ids[part] = real_pool(part)
    real["fresh"], ids["fresh"] = fresh_pool()
    doc = {"format": "adv3d-bench", "version": 1, "topic": "traffic",
           "command": " ".join(["bench/traffic.py"] + sys.argv[1:]),
           "machine": {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count()},
           "real_scenes": ids}
    if args.fit:
        best, history = fit(real["train"])
        doc["fit"] = {"seed": FIT_SEED, "space": SPACE, "scenes_per_candidate": FIT_SCENES,
                      "train_split_seeds": [100_000, 100_000 + FIT_SCENES - 1], "best": best, "history": history}
        prof = make_profile(PROFILES["us101"], best)
        print("\nfitted profile (paste into PROFILES['us101']):\n", prof)
    else:
        prof = PROFILES["us101"]
    default = pool(traffic_samples(load_scene(p)) for p in sorted((ROOT / "scenes" / "highway").glob("*.json.gz")))
    us101 = generated_pool(prof, range(args.scenes), "benchmark")
    rows = {"default (scenes/highway, 100)": default, f"us101 ({args.scenes} scenes)": us101}
    table = {}
    for name, sample in rows.items():
        table[name] = {part: compare(sample, real[part]) for part in real}
    table["real train vs real benchmark"] = {"benchmark": compare(real["train"], real["benchmark"])}
    table["real train vs real fresh"] = {"fresh": compare(real["train"], real["fresh"])}
    doc["profile"] = {k: (asdict(v) if hasattr(v, "__dataclass_fields__") else v) for k, v in asdict(prof).items()}
    doc["summaries"] = {"real train": summary(real["train"]), "real benchmark": summary(real["benchmark"]),
                        "real fresh": summary(real["fresh"]),
                        **{name: summary(sample) for name, sample in rows.items()}}
    doc["ks"] = table
    doc["cpu_s"] = time.process_time() - t0
    print("\nKolmogorov-Smirnov distance to the real recordings (train part = fitted on; benchmark and fresh parts = "
          "held out from the fit)\n")
    parts = list(real)
    print("| generated | " + " | ".join(f"{k} ({part})" for part in parts for k in STATS) + " |")
    print("|---|" + "---|" * (len(parts) * len(STATS)))
    for name in rows:
        t = table[name]
        print(f"| {name} | " + " | ".join(f"{t[part][k]:.3f}" for part in parts for k in STATS) + " |")
    print("\n| sample | speed mean (quartiles) m/s | headway median (quartiles) s | lane changes / vehicle / min |")
    print("|---|---|---|---|")
    for name, s in doc["summaries"].items():
        q, h = s["speed"]["quartiles"], s["headway"]["quartiles"]
        print(f"| {name} | {s['speed']['mean']:.1f} ({q[0]:.1f}-{q[2]:.1f}) | {h[1]:.2f} ({h[0]:.2f}-{h[2]:.2f}) | "
              f"{s['lane_changes_per_vehicle_minute']:.2f} |")
    out = ROOT / "bench" / "results" / ("traffic.fit.json" if args.fit else "traffic.json")
    write_json(out, doc)
    print(f"wrote {out.relative_to(ROOT)} ({doc['cpu_s']:.0f} s CPU)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
