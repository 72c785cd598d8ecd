"""Incremental LiDAR simulation (sensors.incremental): identical frames and identical attack
journals with and without the static-hit cache."""
from __future__ import annotations

import json

import numpy as np
import pytest

from adv3d_runner.sensors.beams import get_model
from adv3d_runner.sensors.incremental import StaticRayCache
from adv3d_runner.sensors.lidar import LidarRig, MountedLidar, simulate_frame
from tests.test_lidar import EGO, assert_frames_equal, box_mesh, crowded_world_and_poses, small_sensor


def _rig():
    return LidarRig([
        MountedLidar(get_model("vlp32c", columns=600), (0.5, 0.0, 1.9, 0.0, 0.0, 0.0)),
        MountedLidar(small_sensor(range_noise=0.02, ray_drop=0.1), (1.5, 0.6, 1.2, 0.05, -0.1, 0.7)),
    ], ego_dimensions=(4.6, 1.9, 1.5))


@pytest.mark.parametrize("dynamic", [[4], [1, 5], [0, 3, 10]])
def test_cached_frames_equal_plain_frames(dynamic):
    """Frames seen again (cache hits) and new ones (misses) give the plain path's points, for
    new shapes of the dynamic actors (bigger ones occlude static actors behind them), an absent
    dynamic actor, and dynamic actors before, between and after static ones."""
    world, poses = crowded_world_and_poses(EGO)
    rig = _rig()
    cache = StaticRayCache(world, dynamic)
    rng = np.random.default_rng(3)
    egos = [EGO, EGO + [0.7, -0.2, 0.05]]
    for query in range(4):
        for a in dynamic:  # a new shape per query, sometimes much larger
            world.set_actor_mesh(a, *box_mesh(*(rng.uniform(0.6, 2.5) * np.array([4.5, 1.9, 1.5]))))
        for ego in egos:
            p = poses.copy()
            if query == 2:
                p[dynamic[0]] = np.nan
            seed = int(rng.integers(1 << 30))
            plain = simulate_frame(world, rig, ego, p, np.random.default_rng(seed))
            cached = simulate_frame(world, rig, ego, p, np.random.default_rng(seed), cache=cache)
            assert_frames_equal(plain, cached)
            assert set(dynamic) & set(np.unique(cached.label)) or query == 2
    assert cache.misses == len(egos) * len(rig.sensors) and cache.hits == 3 * cache.misses
    world.reset_actor_mesh()


def test_cache_refuses_stale_static_geometry():
    """A static actor's new mesh, another rig or another world never reuse stored hits."""
    world, poses = crowded_world_and_poses(EGO)
    rig = _rig()
    cache = StaticRayCache(world, [4])
    simulate_frame(world, rig, EGO, poses, None, cache=cache)
    assert len(cache) == 2
    world.set_actor_mesh(3, *box_mesh(9.0, 2.5, 3.0))  # a static actor changes: stored hits are stale
    assert_frames_equal(simulate_frame(world, rig, EGO, poses, None),
                        simulate_frame(world, rig, EGO, poses, None, cache=cache))
    assert cache.hits == 0 and cache.misses == 4
    simulate_frame(world, _rig(), EGO, poses, None, cache=cache)  # another rig object
    assert cache.hits == 0
    other, _ = crowded_world_and_poses(EGO)
    with pytest.raises(ValueError):
        simulate_frame(other, rig, EGO, poses, None, cache=cache)
    with pytest.raises(ValueError):
        StaticRayCache(world, [99])


def test_cache_memory_bound():
    world, poses = crowded_world_and_poses(EGO)
    rig = LidarRig.single(small_sensor())
    cache = StaticRayCache(world, [4], max_bytes=1)  # nothing fits: never stored, still exact
    a = simulate_frame(world, rig, EGO, poses, None, cache=cache)
    assert len(cache) == 0
    assert_frames_equal(a, simulate_frame(world, rig, EGO, poses, None))
    one = StaticRayCache(world, [4])
    simulate_frame(world, rig, EGO, poses, None, cache=one)
    cache = StaticRayCache(world, [4], max_bytes=int(1.5 * one.nbytes))
    for dx in (0.0, 1.0, 2.0):
        simulate_frame(world, rig, EGO + [dx, 0, 0], poses, None, cache=cache)
    assert len(cache) == 1 and cache.nbytes <= cache.max_bytes  # the newest unused frame dropped
    # a frame served again outlives frames never served again, and the first frames stored stay
    # (every closed-loop query shares them) while the ones of diverged paths come and go
    cache = StaticRayCache(world, [4], max_bytes=int(2.5 * one.nbytes))
    for dx in (0.0, 0.0, 1.0, 2.0, 3.0):
        simulate_frame(world, rig, EGO + [dx, 0, 0], poses, None, cache=cache)
    simulate_frame(world, rig, EGO, poses, None, cache=cache)
    simulate_frame(world, rig, EGO + [1.0, 0, 0], poses, None, cache=cache)
    assert len(cache) == 2 and cache.hits == 3


def _journal(path):
    return [{k: v for k, v in json.loads(line).items() if k != "wall_s"}
            for line in (path / "queries.jsonl").read_text().splitlines()]


def test_attack_journal_identical_with_incremental_simulation(tmp_path, repo_root):
    """An attack (Autonomy-A, open and closed loop) gives the same journal and summary with the
    static-hit cache as without it, byte for byte up to the wall times."""
    from adv3d_runner.attack.config import AttackConfig
    from adv3d_runner.attack.driver import run_attack

    cfg = AttackConfig([str(repo_root / "scenes/highway/highway-benchmark-000000.json.gz")], algo="bo", budget=3,
                       n_initial=2, mode="both", seconds=1.0, autonomy="A")
    run_attack(cfg, tmp_path / "plain", show_progress=False, incremental=False)
    run_attack(cfg, tmp_path / "incremental", show_progress=False, incremental=True)
    plain, inc = _journal(tmp_path / "plain"), _journal(tmp_path / "incremental")
    assert len(plain) == 6 and plain == inc
    lines = [(tmp_path / d / "queries.jsonl").read_text().splitlines() for d in ("plain", "incremental")]
    strip = [[line[:line.rindex(',"wall_s"')] for line in ls] for ls in lines]
    assert strip[0] == strip[1]  # byte for byte up to the wall time
    for name in ("summary.json",):
        a, b = (json.loads((tmp_path / d / name).read_text()) for d in ("plain", "incremental"))
        a.pop("wall_s"), b.pop("wall_s")
        assert a == b
    # the replays of the best shapes (points included) are identical too
    for mode in ("open", "closed"):
        folder = f"scenes/highway-benchmark-000000/{mode}"
        for f in ("replay.points.npz",):
            pa, pb = (np.load(tmp_path / d / folder / f) for d in ("plain", "incremental"))
            assert sorted(pa.files) == sorted(pb.files)
            for k in pa.files:
                np.testing.assert_array_equal(pa[k], pb[k])
