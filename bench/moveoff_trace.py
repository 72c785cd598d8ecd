"""Frame-by-frame trace of one train scene on the LiDAR-free harness of ``bench/real_planner.py``
(noisy ground-truth boxes -> tracker -> shipped predictor -> planner), for finding what holds an
ego at standstill (docs/benchmark.md, "Rolling-in starts"). Per frame: the ego's speed and
acceleration, the bumper gap to the nearest car ahead in its lane and that car's logged and
tracked speed, the plan's first acceleration and its candidate; with ``-k<frame>`` every
current-lane candidate's first and 1 s acceleration, leader speed and gaps, weighted costs, and
the nearest tracks' predicted modes (advance in 2 s, probability). A diagnosis tool: the numbers it
prints are not results.

    .venv/bin/python bench/moveoff_trace.py SCENE START_SPEED CONFIG_JSON [SEED] [-q] [-k<frame> ...]

START_SPEED < 0: the scene's logged speed. Only scenes of the train and the tuned-on recordings
(``scenes/real/split.json``) are accepted, never the fresh part.
"""
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import real_planner as rp  # noqa: E402
from adv3d_runner.autonomy.interface import Detections, EgoState  # noqa: E402
from adv3d_runner.autonomy.planner import SamplingPlanner, PlannerConfig  # noqa: E402
from adv3d_runner.autonomy.stacks import TRACK_MIN_SCORE  # noqa: E402
from adv3d_runner.autonomy.tracker import MultiObjectTracker, TrackerConfig  # noqa: E402
from adv3d_runner.scene.lanemap import LaneMap  # noqa: E402
from adv3d_runner.scene.schema import load_scene  # noqa: E402
from adv3d_runner.scene.real import load_real_split, recording_of  # noqa: E402
from adv3d_runner.autonomy.predictor import DEFAULT_MODEL_DIR, load_predictor  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)
predictor = load_predictor(DEFAULT_MODEL_DIR)


def run(path, v0, over, seed=0, verbose=False, DUMP=()):
    config = PlannerConfig.from_overrides(over, '--config')
    scene = load_scene(path)
    bid = scene.source.details.get("benchmark_id", "")
    rec = load_real_split().recordings
    if not bid or recording_of(bid) not in set(rec["train"]) | set(rec["benchmark"]):
        raise SystemExit(f"{path}: not a scene of a train or tuned-on recording (source.details.benchmark_id {bid!r})")
    poses, valid = scene.all_actor_poses(); dims = scene.actor_dimensions()
    log, log_v = scene.ego_poses(), scene.ego_speeds()
    L, W = float(scene.ego.dimensions[0]), float(scene.ego.dimensions[1])
    v_start = float(log_v[0]) if v0 < 0 else v0
    ego = EgoState(log[0], v_start, length=L, width=W, wheelbase=scene.ego.wheelbase)
    lm = LaneMap.from_scene(scene); planner = SamplingPlanner(config); planner.reset(lm); predictor.reset(lm)
    tracker = MultiObjectTracker(TrackerConfig(min_score=TRACK_MIN_SCORE)); rng = np.random.default_rng(seed)
    T = 50; xs = []; stand = 0; P = []
    for k in range(T):
        near = valid[:, k] & (np.hypot(*(np.nan_to_num(poses[:, k, :2]) - ego.pose[:2]).T) < rp.NOISE["range"])
        idx = np.flatnonzero(near & (rng.random(len(dims)) > rp.NOISE["miss"]))
        det = np.c_[poses[idx, k, :2] + rng.normal(0, rp.NOISE["pos_std"], (len(idx), 2)), dims[idx, :2],
                    poses[idx, k, 2] + rng.normal(0, rp.NOISE["yaw_std"], len(idx))]
        tracks = tracker.update(Detections(det, np.full(len(idx), 0.9)), prior_speed=ego.speed)
        pred = predictor.predict(tracks)
        plan, cands, table = planner.plan_with_scores(ego, pred, tracks)
        if DUMP and k in DUMP and cands is not None:
            d_ = np.hypot(*(tracks.boxes[:, :2] - ego.pose[:2]).T); order = np.argsort(d_)[:3]
            for j in order:
                r = list(pred.track_ids).index(tracks.ids[j]) if tracks.ids[j] in pred.track_ids else None
                if r is None: continue
                tr = pred.trajectories[r]; p0 = tracks.boxes[j, :2]
                adv = [float(np.hypot(*(tr[m, 19] - p0))) for m in range(tr.shape[0])]
                print(f"   track {tracks.ids[j]} dist={d_[j]:.1f} trkv={np.hypot(*tracks.velocities[j]):.2f} modes 2s-advance(prob): " + " ".join(f"{a:.1f}({p:.2f})" for a, p in zip(adv, pred.probabilities[r])))
            for b in range(len(cands)):
                lab = cands.spec.labels[b]
                if not lab.startswith('lane') or '/d+0.0/' not in lab and 'emerg' not in lab: continue
                terms = {kk: round(float(v[b]), 2) for kk, v in table.weighted.items() if abs(v[b]) > 0.005}
                print(f"   k={k} {lab:22s} a0={cands.accel[b,0]:+.2f} a10={cands.accel[b,10]:+.2f} vlead0={cands.leader_speed[b]:.2f} gap0={cands.leader_gap[b,0]:.2f} gap20={cands.leader_gap[b,20]:.2f} tot={table.total[b]:.2f} {'*' if b==table.best else ''} {terms}")
        # true leader: nearest actor ahead within 1.8 m lateral
        c, s_ = math.cos(ego.pose[2]), math.sin(ego.pose[2]); best = None
        for i in range(len(dims)):
            if not valid[i, k]: continue
            dx, dy = poses[i, k, 0] - ego.pose[0], poses[i, k, 1] - ego.pose[1]
            lon, lat = dx * c + dy * s_, -dx * s_ + dy * c
            if lon > 0 and abs(lat) < 1.8 and (best is None or lon < best[0]): best = (lon, i)
        if best:
            i = best[1]; gap = best[0] - L / 2 - dims[i, 0] / 2
            vt = np.hypot(*(poses[i, min(k + 1, poses.shape[1] - 1), :2] - poses[i, k, :2])) / 0.1
            # tracked speed: track nearest to true leader position
            tv = float('nan')
            if len(tracks.ids):
                d = np.hypot(*(tracks.boxes[:, :2] - poses[i, k, :2]).T); j = int(np.argmin(d))
                if d[j] < 2: tv = float(np.hypot(*tracks.velocities[j]))
            line = f"t={k/10:.1f} v={ego.speed:.2f} a={ego.acceleration:+.2f} gap={gap:.2f} vlead={vt:.2f} trk={tv:.2f} a0={plan.acceleration[0]:+.2f} {plan.label}"
        else:
            line = f"t={k/10:.1f} v={ego.speed:.2f} no leader {plan.label}"
        if verbose: print(line)
        xs.append(ego.pose[:2].copy()); P.append(np.array(ego.pose[:3], float)); stand += ego.speed < 0.1
        ego = EgoState(plan.trajectory[1], plan.speed[1], acceleration=float(plan.acceleration[0]), length=L,
                       width=W, wheelbase=scene.ego.wheelbase, time=(k + 1) * 0.1)
    xs.append(ego.pose[:2].copy())
    driven = float(np.sum(np.hypot(*np.diff(np.array(xs), axis=0).T))); logged = float(np.sum(np.hypot(*np.diff(log[:T+1, :2], axis=0).T)))
    print(f"RESULT {Path(path).name} v0={v_start} driven={driven:.2f} logged={logged:.2f} ratio={driven/logged:.2f} stand={stand/10:.1f}s")

    from adv3d_runner.metrics.comfort import driving_comfort
    return driven / logged, stand / 10, driving_comfort(np.array(P), 0.1).jerk

if __name__ == "__main__":
    run(sys.argv[1], float(sys.argv[2]), json.loads(sys.argv[3]), int(sys.argv[4]) if len(sys.argv) > 4 else 0,
        "-q" not in sys.argv, [int(a[2:]) for a in sys.argv if a.startswith("-k")])
