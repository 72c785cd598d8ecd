"""Picture of the real benchmark's drive jerk over LiDAR-noise seeds, per scene, for two planners
(docs/autonomy.md, real traffic): which scenes carry the mean, and how much of it is the sensor's noise.

    .venv/bin/python bench/real_seeds_plot.py [--out docs/img/real_benchmark_seeds.png]

Reads only kept files (``bench/results/``): the planner before (``sanity.planner-53d3561.json``
for seed 0, ``sanity.real-benchmark.seed{1..19}.json``) and the shipped one (``sanity.json``,
``sanity.round10.real-benchmark.seed{1..19}.json``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
PLANNERS = {
    "eighth round (before)": ["sanity.planner-53d3561.json"] + [f"sanity.real-benchmark.seed{s}.json" for s in range(1, 20)],
    "tenth round (shipped)": ["sanity.json"] + [f"sanity.round10.real-benchmark.seed{s}.json" for s in range(1, 20)],
}
TARGET = 1.0  # docs/autonomy.md: mean driving jerk at most 1.0 m/s^3


def drive_jerks(files: list[str]) -> tuple[list[str], np.ndarray]:
    """Scene names and (seeds, scenes) drive jerk (m/s^3) of the real benchmark rows of ``files``."""
    table, names = [], None
    for name in files:
        rows = json.loads((RESULTS / name).read_text())["real"]["rows"]
        scenes = [r["scene"].replace("commonroad-USA_US101-", "").replace("_T-1", "") for r in rows]
        if names is not None and scenes != names:
            raise ValueError(f"{name}: scenes {scenes} differ from {names}")
        names = scenes
        table.append([r["driving_comfort"]["jerk"] for r in rows])
    return names, np.array(table)


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "real_benchmark_seeds.png"))
    args = ap.parse_args()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [3, 1]})
    colours = ("tab:grey", "tab:blue")
    for k, ((label, files), colour) in enumerate(zip(PLANNERS.items(), colours)):
        names, jerk = drive_jerks(files)
        x = np.arange(len(names)) + (k - 0.5) * 0.3
        rng = np.random.default_rng(0)  # horizontal jitter of the dots only
        for i in range(len(names)):
            left.scatter(x[i] + rng.uniform(-0.08, 0.08, len(jerk)), jerk[:, i], s=10, color=colour, alpha=0.7,
                         label=label if i == 0 else None)
        means = jerk.mean(axis=1)
        right.scatter(np.full(len(means), k) + rng.uniform(-0.12, 0.12, len(means)), means, s=12, color=colour)
        right.errorbar(k + 0.3, means.mean(), yerr=2 * means.std(ddof=1) / np.sqrt(len(means)), fmt="o",
                       color="black", capsize=3)
        print(f"{label}: mean over {len(means)} seeds {means.mean():.3f} (sd {means.std(ddof=1):.3f})")
    left.set_xticks(np.arange(len(names)), names)
    left.set_xlabel("real benchmark scene (US-101 recording_variant)")
    left.set_ylabel("drive jerk, m/s^3 (one dot per seed)")
    left.legend(loc="upper right", fontsize=8)
    right.axhline(TARGET, color="tab:red", lw=1, ls="--", label="target 1.0")
    right.set_xticks([0, 1], ["8th", "10th"])
    right.set_xlim(-0.5, 1.6)
    right.set_ylabel("mean over the 7 scenes")
    right.legend(loc="lower left", fontsize=8)
    right.set_title("per seed; black: mean +- 2 se", fontsize=9)
    fig.suptitle("Real benchmark part, 5 s closed loop, Autonomy-A, 20 LiDAR-noise seeds", fontsize=10)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
