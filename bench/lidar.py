"""LiDAR benchmark: per-frame time of the Embree pipeline against a raw Embree cast, culling, beams.

    .venv/bin/python bench/lidar.py [--quick] [--ab COMMIT]

The process is pinned to ONE core (``sched_setaffinity``): Embree's TBB pool (BVH builds) and
numpy then share that core; rays are cast on the calling thread anyway (``sensors/embree.py``:
packets of 8, ``rtcIntersect8``; embreex's ``run``, one ray at a time, where that binding is
unavailable).

World: the first bundled highway scene's background (road, shoulders, markings, barriers,
ground) with N actors placed along its lanes around the ego (library meshes scaled to typical
car/truck boxes when the vehicle library is present, boxes otherwise).

(a) pipeline vs raw Embree, HDL-64E, 30 actors: the full :func:`simulate_frame` (rays, culling,
    actor ray transforms, effects, ego frame output) against ONE Embree call of the same rays on
    a single static BVH holding background + all actors already placed (the ideal for a static
    frame; it needs a BVH rebuild per frame, timed too). "error" = largest range difference
    between the two over rays hit by both, and the share of rays whose hit/miss agrees.
(b) per-frame time against the number of actors (0, 5, 10, 20, 30), with and without culling
    (identical points either way, checked).
(c) points per frame against beam count: VLP-32C, HDL-64E, OS1-128 and generic 32/64/128-beam
    sensors with 2048 columns.
(d) incremental simulation (``sensors.incremental.StaticRayCache``, the attack's per-scene
    cache): HDL-64E, 30 actors, the actor nearest the ego is the dynamic (attacked) one with a
    new shape; a frame whose geometry was seen before (cache hit) against the plain frame and
    the first sight (miss: the static layers cast and stored); points identical in all three.

``--coherent REPEATS``: only the background cast with Embree's coherent query, raw and certified
(``sensors/coherent.py``), against the reference query (``bench/results/lidar_coherent.json``).

``--ab COMMIT``: (a) only, this code's pipeline against COMMIT's ``sensors/lidar.py``, the two
alternating frame by frame in one process (``bench/results/lidar_ab.json``).

Prints the tables and writes ``bench/results/lidar.json`` (``lidar.quick.json`` with --quick)
with machine info and the command.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})  # one core, before Embree starts TBB

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from adv3d_runner.machine import machine_info as _machine_info  # noqa: E402
from adv3d_runner.fileio import write_json  # noqa: E402
from adv3d_runner.sensors.beams import generic_model, get_model  # noqa: E402
from adv3d_runner.sensors.lidar import LidarRig, simulate_frame  # noqa: E402
from adv3d_runner.sensors.raycast import MeshBVH  # noqa: E402
from adv3d_runner.sensors.world import LidarWorld, _box_mesh  # noqa: E402

ACTOR_COUNTS = (0, 5, 10, 20, 30)
DIMS = {"car": (4.6, 1.85, 1.5), "suv": (4.9, 1.95, 1.8), "truck": (9.0, 2.5, 3.4)}


def raw_rays(sensor, world, ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The raw cast's rays: origin (1, 3) float32 at the 1.73 m mount in the world's local frame
    and unit directions (n_rays, 3) float32 turned by the ego's yaw (``ego`` = x, y, yaw)."""
    c, s = np.cos(ego[2]), np.sin(ego[2])
    dirs = np.empty((sensor.n_rays, 3), np.float32)
    dirs[:, 0] = np.float32(c) * sensor.dx - np.float32(s) * sensor.dy
    dirs[:, 1] = np.float32(s) * sensor.dx + np.float32(c) * sensor.dy
    dirs[:, 2] = sensor.dz
    origin = (np.array([ego[0], ego[1], 1.73]) - world.origin).astype(np.float32).reshape(1, 3)
    return origin, dirs

def machine_info() -> dict:
    return _machine_info(
        "numpy", "embreex",
        threads="sensors/embree.py: rtcIntersect8 packets on the calling thread; BVH builds: TBB, pinned to 1 core")


def build_scene_world(n_actors: int, seed: int = 0):
    """Background of the first bundled highway scene, N actors along its lanes near the ego.

    Returns (world, ego_pose (3,), actor_poses (N, 3), description, actor triangle counts)."""
    from adv3d_runner.scene.background import REFLECTIVITY, background_mesh
    from adv3d_runner.scene.schema import load_scene

    scenes = sorted((ROOT / "scenes" / "highway").glob("*.json*"))
    rng = np.random.default_rng(seed)
    if scenes:
        scene = load_scene(scenes[0])
        v, f, kind = background_mesh(scene, scene_dir=scenes[0].parent)
        world = LidarWorld(v, f, REFLECTIVITY[kind])
        ego = scene.ego_poses()[0]
        lanes = [lane.centerline for lane in scene.lanes]
        what = f"{scenes[0].name} background ({len(f)} triangles)"
    else:  # synthetic highway: ground plane and 4 lanes along x
        ground = np.array([[-300, -50, 0], [300, -50, 0], [300, 50, 0], [-300, 50, 0]], float)
        world = LidarWorld(ground, np.array([[0, 1, 2], [0, 2, 3]]), 0.15)
        ego = np.array([0.0, 0.0, 0.0])
        lanes = [np.array([[-300, y], [300, y]]) for y in (-5.25, -1.75, 1.75, 5.25)]
        what = "synthetic flat highway"
    # Candidate slots every 9 m along each lane within 90 m of the ego, ego's own spot excluded.
    slots = []
    for line in lanes:
        seg = np.diff(line, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        s = np.concatenate([[0], np.cumsum(lengths)])
        for q in np.arange(0, s[-1], 9.0):
            k = min(np.searchsorted(s, q, "right") - 1, len(seg) - 1)
            if lengths[k] <= 0:
                continue
            u = (q - s[k]) / lengths[k]
            p = line[k] + u * seg[k]
            d = np.hypot(*(p - ego[:2]))
            if 7.0 < d < 90.0:
                slots.append((p[0], p[1], np.arctan2(seg[k, 1], seg[k, 0])))
    slots = np.array(slots)
    pick = rng.permutation(len(slots))[:n_actors]
    poses = slots[pick] if n_actors else np.zeros((0, 3))
    meshes = actor_meshes()
    tris = []
    for i in range(len(poses)):
        kind, v, f = meshes[i % len(meshes)]
        world.add_actor(i, v, f)
        tris.append(len(f))
    return world, np.asarray(ego, float), poses, what, tris


_MESHES = None


def actor_meshes():
    """A few vehicle meshes in the local frame: library assets scaled to car/suv/truck boxes."""
    global _MESHES
    if _MESHES is not None:
        return _MESHES
    out = []
    try:
        from adv3d_runner.scene.actors import actor_mesh, choose_asset
        from adv3d_runner.shapes.library import load_library

        library = load_library(ROOT / "assets" / "vehicles" / "library.json")
        for cls, dims in (("sedan", DIMS["car"]), ("suv", DIMS["suv"]), ("truck", DIMS["truck"])):
            asset = choose_asset(library, cls, np.array(dims), rule="nearest-size")
            if asset is not None:
                mesh = actor_mesh(library, asset, np.array(dims))
                out.append((f"{cls}:{asset}", np.asarray(mesh.vertices), np.asarray(mesh.faces)))
    except Exception as exc:  # the library is optional for this benchmark
        print(f"(vehicle library unavailable, boxes used: {exc})")
    if not out:
        for cls, dims in DIMS.items():
            box = _box_mesh(dims)
            out.append((f"box:{cls}", np.asarray(box.vertices), np.asarray(box.faces)))
    _MESHES = out
    return out


CLOCK = time.thread_time  # CPU time of this thread: the machine is shared, wall time is not ours
WALL: dict[str, float] = {}


def timed(fn, repeats: int, name: str | None = None):
    """Median CPU time (s) of ``fn`` over ``repeats`` calls, and its last result; the median
    wall time goes to ``WALL[name]``."""
    cpu, wall = [], []
    result = None
    for _ in range(repeats):
        w0, t0 = time.perf_counter(), CLOCK()
        result = fn()
        cpu.append(CLOCK() - t0)
        wall.append(time.perf_counter() - w0)
    if name:
        WALL[name] = float(np.median(wall))
    return float(np.median(cpu)), result


def merged_static_bvh(world: LidarWorld, poses: np.ndarray):
    """One BVH with background + every actor placed at its pose (map frame minus world origin)."""
    verts = [world._bg_vertices]
    faces = [world._bg_faces]
    n = len(world._bg_vertices)
    for i, (x, y, yaw) in enumerate(poses):
        mesh = world._mesh_arrays[world._actors[i].key]
        v, f = mesh
        c, s = np.cos(yaw), np.sin(yaw)
        placed = np.c_[c * v[:, 0] - s * v[:, 1] + x - world.origin[0], s * v[:, 0] + c * v[:, 1] + y - world.origin[1],
                       v[:, 2] - world.origin[2]]
        verts.append(placed)
        faces.append(f + n)
        n += len(v)
    return MeshBVH(np.concatenate(verts), np.concatenate(faces))


def section_a(repeats: int) -> dict:
    world, ego, poses, what, tris = build_scene_world(30)
    rig = LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
    rng = np.random.default_rng(0)
    simulate_frame(world, rig, ego, poses, rng)  # warm-up (ego-box cache)
    embree_times = []

    def pipeline():
        stats = {"clock": CLOCK}
        frame = simulate_frame(world, rig, ego, poses, np.random.default_rng(0), stats=stats)
        embree_times.append(stats["embree_s"])
        return frame

    t_pipe, _ = timed(pipeline, repeats, "pipeline")
    embree_in_pipe = float(np.median(embree_times))
    # Raw: one cast of the same rays on a merged static BVH.
    sensor = rig.sensors[0]
    origin, dirs = raw_rays(sensor, world, ego)
    t_build, merged = timed(lambda: merged_static_bvh(world, poses), max(2, repeats // 3))

    def raw():
        t = np.full(sensor.n_rays, sensor.model.max_range, np.float32)
        prim, _ = merged.intersect(origin, dirs, t)
        return t, prim

    t_raw, (t_ref, prim_ref) = timed(raw, repeats, "raw")
    # Error: pipeline without effects vs the merged cast, per ray (ray order is the same).
    ideal = simulate_frame(world, LidarRig.single(sensor.model.with_overrides(min_range=0.0), mount=(0, 0, 1.73, 0, 0, 0)),
                           ego, poses, None)
    hit_ref = (prim_ref >= 0) & (t_ref < sensor.model.max_range)
    # Same ray order in both (the sensor's ray table), so compare ray by ray where both hit.
    agree = ideal.distance.size == int(hit_ref.sum())
    max_err = float(np.abs(ideal.distance - t_ref[hit_ref]).max()) if agree else float("nan")
    row = {
        "world": what, "actors": 30, "actor_triangles": int(sum(tris)), "rays": sensor.n_rays,
        "pipeline_ms": 1e3 * t_pipe, "pipeline_embree_ms": 1e3 * embree_in_pipe,
        "raw_merged_cast_ms": 1e3 * t_raw, "merged_bvh_build_ms": 1e3 * t_build,
        "overhead_vs_raw_cast": t_pipe / t_raw - 1.0,
        "overhead_vs_own_embree": t_pipe / embree_in_pipe - 1.0,
        "wall_pipeline_ms": 1e3 * WALL["pipeline"], "wall_raw_cast_ms": 1e3 * WALL["raw"],
        "hits_pipeline": int(ideal.distance.size), "hits_raw": int(hit_ref.sum()),
        "max_range_diff_m": max_err,
    }
    print("\n(a) HDL-64E frame, 30 actors: full pipeline vs raw Embree on the same rays (median CPU ms)")
    print(f"  world: {what}; actor triangles {sum(tris)}; rays {sensor.n_rays}")
    print(f"  {'full pipeline':34s} {row['pipeline_ms']:8.2f}   (of which inside Embree {row['pipeline_embree_ms']:.2f})")
    print(f"  {'raw cast, one merged static BVH':34s} {row['raw_merged_cast_ms']:8.2f}   "
          f"(+ BVH rebuild per frame {row['merged_bvh_build_ms']:.2f})")
    print(f"  overhead vs raw cast {100 * row['overhead_vs_raw_cast']:+.1f}%   vs its own Embree calls "
          f"{100 * row['overhead_vs_own_embree']:+.1f}%")
    print(f"  hits {row['hits_pipeline']} vs {row['hits_raw']}, largest per-ray range difference "
          f"{row['max_range_diff_m']:.2e} m")
    return row


def section_b(repeats: int) -> list[dict]:
    rows = []
    print("\n(b) HDL-64E per-frame time against actors (median CPU ms; identical points with/without culling)")
    print(f"  {'actors':>6s} {'cull ms':>9s} {'no-cull ms':>11s} {'speed-up':>9s} {'actor rays cull':>16s} "
          f"{'no cull':>10s} {'points':>8s} {'same':>5s}")
    rig = LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
    for n in ACTOR_COUNTS:
        world, ego, poses, _, _ = build_scene_world(n)
        simulate_frame(world, rig, ego, poses, None)
        st_c, st_n = {"clock": CLOCK}, {"clock": CLOCK}
        t_c, f_c = timed(lambda: simulate_frame(world, rig, ego, poses, np.random.default_rng(1), stats=st_c), repeats)
        t_n, f_n = timed(lambda: simulate_frame(world, rig, ego, poses, np.random.default_rng(1), cull=False,
                                                stats=st_n), max(1, repeats // 3))
        same = all(np.array_equal(getattr(f_c, k), getattr(f_n, k)) for k in ("points", "ring", "label", "distance"))
        row = {"actors": n, "cull_ms": 1e3 * t_c, "no_cull_ms": 1e3 * t_n,
               "actor_rays_cull": st_c.get("actor_rays", 0) // repeats,
               "actor_rays_no_cull": st_n.get("actor_rays", 0) // max(1, repeats // 3),
               "points": len(f_c), "actor_points": int((f_c.label >= 0).sum()), "identical": bool(same)}
        rows.append(row)
        print(f"  {n:6d} {row['cull_ms']:9.2f} {row['no_cull_ms']:11.2f} {t_n / t_c:9.2f} "
              f"{row['actor_rays_cull']:16d} {row['actor_rays_no_cull']:10d} {row['points']:8d} {str(same):>5s}")
    return rows


def section_c(repeats: int) -> list[dict]:
    rows = []
    world, ego, poses, _, _ = build_scene_world(30)
    models = [get_model("vlp32c"), get_model("hdl64"), get_model("os1-128")]
    models += [generic_model(b, 10.0, -25.0, 2048, 120.0, name=f"generic-{b}x2048") for b in (32, 64, 128)]
    print("\n(c) points per frame against beam count (30 actors, median CPU ms)")
    print(f"  {'model':18s} {'beams':>5s} {'rays':>8s} {'points':>8s} {'on actors':>9s} {'ms':>8s} {'us/ray':>7s}")
    for model in models:
        rig = LidarRig.single(model, mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
        simulate_frame(world, rig, ego, poses, None)
        t, frame = timed(lambda: simulate_frame(world, rig, ego, poses, np.random.default_rng(2)), repeats)
        row = {"model": model.name, "beams": model.beams, "rays": model.rays, "points": len(frame),
               "actor_points": int((frame.label >= 0).sum()), "ms": 1e3 * t}
        rows.append(row)
        print(f"  {model.name:18s} {model.beams:5d} {model.rays:8d} {len(frame):8d} {row['actor_points']:9d} "
              f"{row['ms']:8.2f} {1e6 * t / model.rays:7.3f}")
    return rows


def section_d(repeats: int) -> dict:
    from adv3d_runner.sensors.incremental import StaticRayCache

    world, ego, poses, _, _ = build_scene_world(30)
    rig = LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
    nearest = int(np.argmin(np.hypot(*(poses[:, :2] - ego[:2]).T)))
    _, v, f = actor_meshes()[0]
    world.set_actor_mesh(nearest, v * np.array([1.2, 1.15, 1.1]), f)  # an "attacked" shape
    simulate_frame(world, rig, ego, poses, None)
    st_plain, st_hit = {"clock": CLOCK}, {"clock": CLOCK}
    t_plain, plain = timed(lambda: simulate_frame(world, rig, ego, poses, np.random.default_rng(4), stats=st_plain),
                           repeats, "plain")
    misses = []

    def miss():
        cache = StaticRayCache(world, [nearest])
        t0 = CLOCK()
        frame = simulate_frame(world, rig, ego, poses, np.random.default_rng(4), cache=cache)
        misses.append(CLOCK() - t0)
        return frame, cache

    for _ in range(max(3, repeats // 3)):
        first, cache = miss()
    t_miss = float(np.median(misses))
    t_hit, hit = timed(lambda: simulate_frame(world, rig, ego, poses, np.random.default_rng(4), cache=cache,
                                              stats=st_hit), repeats, "hit")
    same = all(np.array_equal(getattr(a, k), getattr(b, k)) for a in (first, hit)
               for b in (plain,) for k in ("points", "ring", "label", "distance"))
    n_plain = repeats
    row = {"dynamic_actor": nearest, "plain_ms": 1e3 * t_plain, "miss_ms": 1e3 * t_miss, "hit_ms": 1e3 * t_hit,
           "plain_embree_ms": 1e3 * st_plain["embree_s"] / n_plain, "hit_embree_ms": 1e3 * st_hit["embree_s"] / repeats,
           "hit_rays_cast": st_hit["rays_cast"] // repeats, "plain_rays_cast": st_plain["rays_cast"] // n_plain,
           "speed_up_hit": t_plain / t_hit, "cache_megabytes_per_frame": cache.nbytes / 2**20, "identical": bool(same)}
    print("\n(d) incremental simulation, HDL-64E, 30 actors, the nearest one attacked (median CPU ms)")
    print(f"  plain frame {row['plain_ms']:.2f} (Embree {row['plain_embree_ms']:.2f}, {row['plain_rays_cast']} rays cast)")
    print(f"  first sight (cast + store) {row['miss_ms']:.2f}")
    print(f"  seen before (cache hit) {row['hit_ms']:.2f} (Embree {row['hit_embree_ms']:.2f}, {row['hit_rays_cast']} rays "
          f"cast): x{row['speed_up_hit']:.1f}; {row['cache_megabytes_per_frame']:.2f} MB stored per frame; "
          f"identical points: {same}")
    return row


def section_ab(base: str, repeats: int) -> dict:
    """(a) against another commit's ``sensors/lidar.py``, interleaved frame by frame in this
    process (same world, rays and load): pipeline and Embree CPU ms per frame for both, and
    whether the frames are the same bytes."""
    import adv3d_runner.sensors.lidar as new

    old = _module_at(base)
    world, ego, poses, what, tris = build_scene_world(30)
    mods = {"base": old, "this": new}
    rigs = {k: m.LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
            for k, m in mods.items()}
    cpu = {k: [] for k in mods}
    emb = {k: [] for k in mods}
    frames = {}
    for k, m in mods.items():  # warm-up
        frames[k] = m.simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(0))
    for r in range(repeats):
        for k in (("base", "this") if r % 2 else ("this", "base")):
            stats = {"clock": CLOCK}
            t0 = CLOCK()
            mods[k].simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(0), stats=stats)
            cpu[k].append(CLOCK() - t0)
            emb[k].append(stats["embree_s"])
    same = all(getattr(frames["base"], f).tobytes() == getattr(frames["this"], f).tobytes()
               for f in ("points", "ring", "label", "distance"))
    out = {"world": what, "actors": len(poses), "base": base, "frames_identical": same}
    for k in mods:
        p, e = 1e3 * float(np.median(cpu[k])), 1e3 * float(np.median(emb[k]))
        out[k] = {"pipeline_ms": p, "embree_ms": e, "other_ms": p - e, "pipeline_over_embree": p / e}
        print(f"{k:5s} pipeline {p:6.2f} ms  Embree {e:6.2f} ms  rest {p - e:5.2f} ms  ratio {p / e:.3f}")
    print(f"frames identical: {same}")
    return out


def _module_at(commit: str):
    """``sensors/lidar.py`` as it was at ``commit``, loaded as its own module."""
    import subprocess
    import types

    src = subprocess.run(["git", "show", f"{commit}:adv3d_runner/sensors/lidar.py"], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    mod = types.ModuleType(f"adv3d_runner.sensors._lidar_{commit}")
    mod.__package__ = "adv3d_runner.sensors"
    sys.modules[mod.__name__] = mod  # dataclasses look their module up
    exec(compile(src, f"{commit}:adv3d_runner/sensors/lidar.py", "exec"), mod.__dict__)
    return mod


def section_ratio(repeats: int, base: str | None) -> dict:
    """(a)'s ratio measured pair by pair: the pipeline (this code, and ``base``'s
    ``sensors/lidar.py`` when given) and the raw cast of the same rays on the merged static BVH
    alternate call by call in this process (the order rotates every repeat), so both see the
    same load; each repeat gives one ratio pipeline / raw from adjacent calls. Reports the
    median and the spread (quartiles, 10-90 %) of those ratios and of the CPU times."""
    import adv3d_runner.sensors.lidar as this

    _patch_world_recording()
    world, ego, poses, what, tris = build_scene_world(30)
    mods = {"this": this}
    if base:
        mods["base"] = _module_at(base)
    rigs = {k: m.LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
            for k, m in mods.items()}
    sensor = rigs["this"].sensors[0]
    origin, dirs = raw_rays(sensor, world, ego)
    merged = merged_static_bvh(world, poses)

    def raw():
        t = np.full(sensor.n_rays, sensor.model.max_range, np.float32)
        merged.intersect(origin, dirs, t)

    calls = {"raw": raw}
    frames = {}
    for k, m in mods.items():
        frames[k] = m.simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(0))  # warm-up
        calls[k] = (lambda m=m, rig=rigs[k]: m.simulate_frame(world, rig, ego, poses, np.random.default_rng(0)))
    raw()
    names = list(calls)
    cpu = {k: [] for k in names}
    for r in range(repeats):
        for k in names[r % len(names):] + names[:r % len(names)]:
            t0 = CLOCK()
            calls[k]()
            cpu[k].append(CLOCK() - t0)
    out = {"world": what, "actors": len(poses), "actor_triangles": int(sum(tris)), "rays": sensor.n_rays,
           "repeats": repeats, "base": base, "order": "rotating: " + ", ".join(names)}

    def spread(x):
        q = np.percentile(x, [10, 25, 50, 75, 90])
        return {"median": float(q[2]), "q25": float(q[1]), "q75": float(q[3]), "p10": float(q[0]), "p90": float(q[4])}

    raw_t = np.array(cpu["raw"])
    out["raw_cast_ms"] = spread(1e3 * raw_t)
    print(f"\n(ratio) HDL-64E, 30 actors, {repeats} repeats alternating {', '.join(names)} (CPU ms / ratio)")
    print(f"  {'raw cast':10s} median {1e3 * np.median(raw_t):6.2f} ms  IQR {out['raw_cast_ms']['q25']:.2f}-"
          f"{out['raw_cast_ms']['q75']:.2f}")
    for k in mods:
        t = np.array(cpu[k])
        ratio = t / raw_t
        out[k] = {"pipeline_ms": spread(1e3 * t), "ratio_pipeline_over_raw": spread(ratio),
                  "ratio_of_medians": float(np.median(t) / np.median(raw_t))}
        q = out[k]["ratio_pipeline_over_raw"]
        print(f"  {k:10s} median {1e3 * np.median(t):6.2f} ms  ratio median {q['median']:.3f} "
              f"(IQR {q['q25']:.3f}-{q['q75']:.3f}, 10-90% {q['p10']:.3f}-{q['p90']:.3f}); "
              f"ratio of medians {out[k]['ratio_of_medians']:.3f}")
    out["breakdown_this"] = _breakdown(this, world, rigs["this"], ego, poses)
    if base:
        out["frames_identical_to_base"] = all(
            getattr(frames["base"], f).tobytes() == getattr(frames["this"], f).tobytes()
            for f in ("points", "ring", "label", "sensor", "distance"))
        print(f"  frames identical to {base}: {out['frames_identical_to_base']}")
    return out


def _breakdown(mod, world, rig, ego, poses, repeats: int = 41) -> dict:
    """Where one frame's CPU time goes (after the timed rounds, instrumented, so not part of
    the ratio): Embree calls on the background and on the actors, the sensor effects, and the
    noise and drop draws alone (the same sizes drawn from a fresh generator, as the effects
    draw them); ms per frame."""
    from adv3d_runner.sensors import raycast

    acc = {"background_embree": 0.0, "actor_embree": 0.0, "actor_calls": 0, "effects": 0.0}
    intersect, effects = raycast.MeshBVH.intersect, mod._effects
    sizes = []

    def timed_intersect(self, *a):
        t0 = CLOCK()
        r = intersect(self, *a)
        key = "background_embree" if self is world.background else "actor_embree"
        acc[key] += CLOCK() - t0
        acc["actor_calls"] += key == "actor_embree"
        return r

    def timed_effects(*a):
        t0 = CLOCK()
        r = effects(*a)
        acc["effects"] += CLOCK() - t0
        return r

    raycast.MeshBVH.intersect, mod._effects = timed_intersect, timed_effects
    try:
        total = 0.0
        for _ in range(repeats):
            t0 = CLOCK()
            frame = mod.simulate_frame(world, rig, ego, poses, np.random.default_rng(0))
            total += CLOCK() - t0
            sizes.append(len(frame))
    finally:
        raycast.MeshBVH.intersect, mod._effects = intersect, effects
    model = rig.sensors[0].model
    valid = int(sizes[-1] / (1.0 - model.ray_drop))  # about the returns before the drop
    try:  # the effects' own draws (a compiled loop giving numpy's values, docs/lidar.md), numpy's before
        from adv3d_runner.sensors.draws import draw_f32
    except ImportError:
        def draw_f32(rng, n_gauss, n_uniform):
            return rng.standard_normal(n_gauss, dtype=np.float32), rng.random(n_uniform, dtype=np.float32)
    draws = []
    for _ in range(repeats):
        rng = np.random.default_rng(0)
        t0 = CLOCK()
        draw_f32(rng, valid, valid)
        draws.append(CLOCK() - t0)
    out = {k: 1e3 * v / repeats for k, v in acc.items() if k != "actor_calls"}
    out["actor_calls"] = acc["actor_calls"] / repeats
    out["frame"] = 1e3 * total / repeats
    out["rest"] = out["frame"] - out["background_embree"] - out["actor_embree"] - out["effects"]
    out["draws_in_effects"] = 1e3 * float(np.median(draws))
    print("  breakdown (this, ms per frame, instrumented): " + ", ".join(f"{k} {v:.2f}" for k, v in out.items()))
    return out


def _sensors_at(commit: str):
    """``adv3d_runner/sensors`` as it was at ``commit``, as the package
    ``adv3d_runner._sensors_COMMIT`` (its relative imports resolve inside it)."""
    import importlib
    import subprocess
    import tempfile
    import types

    folder = Path(tempfile.mkdtemp(prefix="sensors-")) / "sensors"
    folder.mkdir()
    names = subprocess.run(["git", "ls-tree", "--name-only", f"{commit}:adv3d_runner/sensors"], cwd=ROOT,
                           capture_output=True, text=True, check=True).stdout.split()
    for name in names:
        if name.endswith(".py"):
            (folder / name).write_text(subprocess.run(["git", "show", f"{commit}:adv3d_runner/sensors/{name}"],
                                                      cwd=ROOT, capture_output=True, text=True, check=True).stdout)
    pkg = types.ModuleType(f"adv3d_runner._sensors_{commit}")
    pkg.__path__ = [str(folder)]
    pkg.__package__ = pkg.__name__
    sys.modules[pkg.__name__] = pkg
    return (importlib.import_module(f"{pkg.__name__}.lidar"), importlib.import_module(f"{pkg.__name__}.incremental"))


def section_cache_ab(repeats: int, base: str) -> dict:
    """(d)'s two cache paths against ``base``'s ``sensors`` package, alternating in this process:
    a frame seen before (hit) and a frame cast and stored (miss: a new cache each time);
    median CPU ms and whether the frames are the same bytes."""
    import adv3d_runner.sensors.incremental as inc
    import adv3d_runner.sensors.lidar as lid

    world, ego, poses, _, _ = build_scene_world(30)
    nearest = int(np.argmin(np.hypot(*(poses[:, :2] - ego[:2]).T)))
    _, v, f = actor_meshes()[0]
    world.set_actor_mesh(nearest, v * np.array([1.2, 1.15, 1.1]), f)
    mods = {"this": (lid, inc), "base": _sensors_at(base)}
    rigs = {k: m[0].LidarRig.single(get_model("hdl64"), mount=(0, 0, 1.73, 0, 0, 0), ego_dimensions=(4.6, 1.9, 1.5))
            for k, m in mods.items()}
    caches = {k: m[1].StaticRayCache(world, [nearest]) for k, m in mods.items()}
    frames = {}
    for k, (lm, _) in mods.items():
        frames[k] = [lm.simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(4), cache=caches[k])
                     for _ in range(2)]  # a miss, then a hit
    cpu = {k: {"hit": [], "miss": []} for k in mods}
    for r in range(repeats):
        for k in (("this", "base") if r % 2 else ("base", "this")):
            lm, im = mods[k]
            t0 = CLOCK()
            lm.simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(4), cache=caches[k])
            cpu[k]["hit"].append(CLOCK() - t0)
            fresh = im.StaticRayCache(world, [nearest])
            t0 = CLOCK()
            lm.simulate_frame(world, rigs[k], ego, poses, np.random.default_rng(4), cache=fresh)
            cpu[k]["miss"].append(CLOCK() - t0)
    same = all(getattr(a, f).tobytes() == getattr(b, f).tobytes()
               for a, b in ((frames["this"][0], frames["base"][0]), (frames["this"][1], frames["base"][1]))
               for f in ("points", "ring", "label", "sensor", "distance"))
    out = {"base": base, "dynamic_actor": nearest, "repeats": repeats, "frames_identical_to_base": same}
    print(f"\n(cache) static-hit cache paths, {repeats} repeats alternating this and {base} (median CPU ms)")
    for k in mods:
        out[k] = {p: 1e3 * float(np.median(cpu[k][p])) for p in ("hit", "miss")}
        print(f"  {k:5s} hit {out[k]['hit']:6.2f}  miss {out[k]['miss']:6.2f}")
    print(f"  frames identical: {same}")
    return out


COHERENT_SCENES = ("scenes/highway/highway-benchmark-000010.json.gz", "scenes/highway/highway-benchmark-000000.json.gz",
                   "scenes/real/USA_US101-9_3_T-1.json.gz")


def section_coherent(repeats: int) -> list[dict]:
    """The background cast of HDL-64E frames (10 logged ego poses per scene): the reference
    query (packets of 8), Embree's raw coherent query (packets of 8 and 16), and the certified
    coherent cast (``MeshBVH(..., coherent=True)``, docs/lidar.md) with its parts: the coherent
    query, the certification loop, the uncertain hits and the misses cast again. Checks that
    the certified cast equals the reference bit for bit and counts the rays where the raw
    coherent query differs."""
    from adv3d_runner.scene import load_scene
    from adv3d_runner.sensors import coherent, embree
    from adv3d_runner.sensors.world import rig_from_scene, world_from_scene
    from adv3d_runner.sim.episode import default_library

    rows = []
    for path in COHERENT_SCENES:
        scene = load_scene(ROOT / path)
        world = world_from_scene(scene, default_library())
        bvh, sensor = world.background, rig_from_scene(scene).sensors[0]
        if bvh.certificates is None:  # the world casts plainly on this ISA: certify a copy to compare
            from adv3d_runner.sensors.raycast import MeshBVH

            bvh = MeshBVH(bvh._scene._vertices[:-1], bvh._scene._faces[:-1], coherent=True)
        cert, sc = bvh.certificates, bvh._scene
        t0 = time.process_time()
        coherent.face_certificates(sc._vertices[:-1], sc._faces[:-1])
        build_s = time.process_time() - t0
        times: dict[str, list[float]] = {}
        counts = {"rays": 0, "recast_hits": 0, "recast_misses": 0, "raw_coherent_differs": 0}
        same = True
        for k in np.linspace(0, len(scene.ego_poses()) - 1, 10).astype(int):
            origin, dirs = raw_rays(sensor, world, scene.ego_poses()[k])
            limit = np.full(len(dirs), sensor.model.max_range, np.float32)
            for _ in range(repeats):
                def clock(name, fn):
                    a = time.thread_time()
                    out = fn()
                    times.setdefault(name, []).append(time.thread_time() - a)
                    return out
                t_ref = limit.copy()
                p_ref = clock("reference_8", lambda: sc.intersect(origin, dirs, t_ref))
                t_raw = limit.copy()
                p_raw = clock("raw_coherent_16", lambda: sc.intersect(origin, dirs, t_raw, coherent=True))
                t8 = limit.copy()
                clock("raw_coherent_8", lambda: embree._cast(sc._scene, origin, dirs, t8, np.empty(len(dirs), np.int32),
                                                              embree._NO_UV, embree.COHERENT, 8))
                t_new = limit.copy()
                p_new = clock("certified", lambda: bvh.intersect(origin, dirs, t_new)[0])
                same &= bool(np.array_equal(t_new.view(np.int32), t_ref.view(np.int32)) and np.array_equal(p_new, p_ref))
                # the certified cast's parts
                t = limit.copy()
                uv = np.empty((len(dirs), 2), np.float32)
                prim = clock("part_coherent", lambda: sc.intersect(origin, dirs, t, uv=uv, coherent=True))
                redo = clock("part_certify", lambda: coherent.uncertain_rays(
                    prim, t, uv, dirs, limit, cert.crowded, cert.altitudes, cert.normals, cert.cell_slot,
                    cert.cell_frame, cert.cell_crowded, cert.margin, coherent.MIN_SIN_INCIDENCE))
                miss = prim[redo] < 0
                for name, idx in (("part_recast_hits", redo[~miss]), ("part_recast_misses", redo[miss])):
                    tt = limit[idx]
                    d = np.ascontiguousarray(dirs[idx])
                    clock(name, lambda: sc.intersect(origin, d, tt))
            counts["rays"] += len(dirs)
            counts["recast_hits"] += int((~miss).sum())
            counts["recast_misses"] += int(miss.sum())
            counts["raw_coherent_differs"] += int((p_raw != p_ref).sum() + ((p_raw == p_ref) & (t_raw != t_ref)).sum())
        row = {"scene": Path(path).name, "faces": int(len(cert.crowded)), "crowded_faces": int(cert.crowded.sum()),
               "certificates_s": build_s, "frames": 10, "repeats": repeats,
               "ms_per_frame": {k: 1e3 * float(np.median(v)) for k, v in times.items()},
               "per_frame": {k: v / 10 for k, v in counts.items()}, "certified_equals_reference": same}
        rows.append(row)
        ms = row["ms_per_frame"]
        print(f"{row['scene']:34s} reference {ms['reference_8']:5.2f}  raw coherent 8 {ms['raw_coherent_8']:5.2f} "
              f"16 {ms['raw_coherent_16']:5.2f}  certified {ms['certified']:5.2f} (coherent {ms['part_coherent']:.2f}, "
              f"certify {ms['part_certify']:.2f}, hits again {ms['part_recast_hits']:.2f}, misses again "
              f"{ms['part_recast_misses']:.2f}) ms; per frame {row['per_frame']}; equal: {same}")
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--ab", metavar="COMMIT", default=None,
                        help="only (a), against COMMIT's sensors/lidar.py, interleaved (bench/results/lidar_ab.json)")
    parser.add_argument("--ratio", type=int, metavar="REPEATS", default=None,
                        help="only the pipeline / raw cast ratio, pair by pair, REPEATS rounds "
                             "(bench/results/lidar_ratio.json)")
    parser.add_argument("--base", metavar="COMMIT", default=None,
                        help="with --ratio: also COMMIT's sensors/lidar.py, in the same rotation")
    parser.add_argument("--out", default=None, help="with --ratio or --coherent: the JSON to write")
    parser.add_argument("--coherent", type=int, metavar="REPEATS", default=None,
                        help="only the coherent background casts against the reference query "
                             "(bench/results/lidar_coherent.json)")
    args = parser.parse_args()
    if args.coherent:
        result = {"benchmark": "lidar_coherent", "command": " ".join([Path(sys.executable).name] + sys.argv),
                  "machine": machine_info(), "load_average_before": list(os.getloadavg()),
                  "timing": "median CPU time of the (single) thread per call, time.thread_time",
                  "scenes": section_coherent(args.coherent)}
        result["load_average_after"] = list(os.getloadavg())
        out = Path(args.out) if args.out else ROOT / "bench" / "results" / "lidar_coherent.json"
        write_json(out, result)
        print(f"\nwrote {out}")
        return 0
    if args.ratio:
        result = {"benchmark": "lidar_ratio", "command": " ".join([Path(sys.executable).name] + sys.argv),
                  "machine": machine_info(), "load_average_before": list(os.getloadavg()),
                  "timing": "CPU time of the (single) thread per call, time.thread_time; pipeline(s) and raw "
                            "cast alternate call by call",
                  "ratio": section_ratio(args.ratio, args.base)}
        if args.base:
            result["cache_paths"] = section_cache_ab(max(21, args.ratio // 5), args.base)
        result["load_average_after"] = list(os.getloadavg())
        out = Path(args.out) if args.out else ROOT / "bench" / "results" / "lidar_ratio.json"
        write_json(out, result)
        print(f"\nwrote {out}")
        return 0
    if args.ab:
        repeats = 101
        result = {"benchmark": "lidar_ab", "command": " ".join([Path(sys.executable).name] + sys.argv),
                  "repeats": repeats, "machine": machine_info(), "load_average_before": list(os.getloadavg()),
                  "timing": "median CPU time of the (single) thread, time.thread_time; the two versions "
                            "alternate frame by frame",
                  "a_pipeline_vs_embree": section_ab(args.ab, repeats)}
        result["load_average_after"] = list(os.getloadavg())
        out = ROOT / "bench" / "results" / "lidar_ab.json"
        write_json(out, result)
        print(f"\nwrote {out.relative_to(ROOT)}")
        return 0
    repeats = 5 if args.quick else 21
    # The merged-BVH reference needs the raw arrays: record them as actors are added.
    _patch_world_recording()
    info = machine_info()
    print(f"LiDAR benchmark ({'quick' if args.quick else 'full'}), {info['cpu']}, cores used: {info['cores_used']}")
    result = {
        "benchmark": "lidar", "command": " ".join([Path(sys.executable).name] + sys.argv), "quick": args.quick,
        "repeats": repeats, "machine": info,
        "timing": "median CPU time of the (single) thread, time.thread_time; wall medians for (a) too",
        "a_pipeline_vs_raw": section_a(repeats),
        "b_actors_culling": section_b(repeats),
        "c_beams": section_c(repeats),
        "d_incremental": section_d(repeats),
    }
    out = ROOT / "bench" / "results" / ("lidar.quick.json" if args.quick else "lidar.json")
    write_json(out, result)
    print(f"\nwrote {out.relative_to(ROOT)}")
    return 0


def _patch_world_recording() -> None:
    """Record the background and actor mesh arrays on LidarWorld (the core does not keep them)."""
    init, bvh_for = LidarWorld.__init__, LidarWorld._bvh_for

    def init_rec(self, vertices, faces, *a, **kw):
        init(self, vertices, faces, *a, **kw)
        self._bg_vertices = np.asarray(vertices, np.float64).reshape(-1, 3) - self.origin
        self._bg_faces = np.asarray(faces, np.int64).reshape(-1, 3)
        self._mesh_arrays = {}

    def bvh_rec(self, vertices, faces):
        key = bvh_for(self, vertices, faces)
        if key is not None:
            self._mesh_arrays[key] = (np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
        return key

    LidarWorld.__init__ = init_rec
    LidarWorld._bvh_for = bvh_rec


if __name__ == "__main__":
    sys.exit(main())
