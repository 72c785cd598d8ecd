"""The LiDAR pipeline's output pinned to its bytes: sha256 of every frame array for a fixed
scene, rig and seed. Written before the pipeline was sped up, so any optimisation that changes
one bit of a point, a label or a random draw fails here.

Bits hold only on one numerical configuration (docs/reliability.md): Embree's ISA and numpy's
SIMD target change the last bits of hits and of float32 transcendental functions. So the
digests are kept per configuration (``tests/data/lidar_pinned.json``, keyed by
``machine.numerical_config()["key"]``) and checked only where the running configuration has
them. Record them for the configuration you run (after checking, e.g. with the fast suite,
that the pipeline is right there)::

    python -m tests.test_lidar_pinned --record
    adv3d numerics --emulate avx2 -- python -m tests.test_lidar_pinned --record
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.sensors.beams import get_model
from adv3d_runner.sensors.incremental import StaticRayCache
from adv3d_runner.sensors.lidar import LidarRig, MountedLidar, simulate_frame
from adv3d_runner.sensors.world import world_from_scene

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
FIELDS = ("points", "ring", "label", "sensor", "distance")

PINNED_FILE = ROOT / "tests" / "data" / "lidar_pinned.json"


def digest(frame) -> str:
    h = hashlib.sha256()
    for name in FIELDS:
        a = np.ascontiguousarray(getattr(frame, name))
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def pinned_frames():
    """(name, frame) for: the scene's HDL-64E at three frames with noise and drop, one ideal
    frame, a two-sensor rig (a VLP-32C with per-laser azimuths mounted off the ego box) with
    an ego body mesh, and cache misses and hits with an attacked actor's new shape."""
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.shapes.library import load_library

    scene = load_scene(SCENE)
    library = load_library(ROOT / "assets" / "vehicles" / "library.json")
    world = world_from_scene(scene, library, scene_dir=SCENE.parent)
    egos = scene.ego_poses()
    poses, valid = scene.all_actor_poses()

    def actors(f):
        p = poses[:, f].copy()
        p[~valid[:, f]] = np.nan
        return p

    rig = LidarRig([MountedLidar(get_model("hdl64"), (0.0, 0.0, 1.73, 0.0, 0.0, 0.0))],
                   ego_dimensions=(4.6, 1.9, 1.5))
    out = []
    for f, seed in ((0, 11), (20, 12), (40, 13)):
        out.append((f"hdl64-frame{f}", simulate_frame(world, rig, egos[f], actors(f), np.random.default_rng(seed))))
    out.append(("hdl64-frame10-ideal", simulate_frame(world, rig, egos[10], actors(10), None)))
    # The nearest present actor gets a new shape and is the attacked (dynamic) one.
    p0 = actors(0)
    d = np.hypot(p0[:, 0] - egos[0][0], p0[:, 1] - egos[0][1])
    a = int(np.nanargmin(d))
    rng = np.random.default_rng(5)
    v = np.c_[rng.uniform(-2.5, 2.5, (60, 2)), rng.uniform(0.0, 2.0, 60)]
    import trimesh

    hull = trimesh.convex.convex_hull(v)
    world.set_actor_mesh(world.actor_ids[a], np.asarray(hull.vertices), np.asarray(hull.faces))
    two = LidarRig([MountedLidar(get_model("hdl64", columns=1000), (0.2, 0.0, 1.9, 0.0, 0.0, 0.0)),
                    MountedLidar(get_model("vlp32c"), (2.6, 0.4, 1.0, 0.03, -0.05, 0.6))],
                   ego_dimensions=(4.6, 1.9, 1.5))
    world.set_ego_mesh(*_ego_body())
    out.append(("two-sensors-ego-body-frame5", simulate_frame(world, two, egos[5], actors(5), np.random.default_rng(21))))
    world.set_ego_mesh(None, None)
    cache = StaticRayCache(world, [a])
    for f, what in ((0, "miss"), (30, "miss"), (0, "hit"), (30, "hit")):
        out.append((f"cache-{what}-frame{f}", simulate_frame(world, rig, egos[f], actors(f), np.random.default_rng(31),
                                                       cache=cache)))
    assert cache.hits == 2 and cache.misses == 2
    assert all(a in frame.label for _, frame in out[-4:])  # the attacked actor is seen
    world.reset_actor_mesh()
    return dict(out)


def _ego_body():
    """A low box for the ego's body with the hood in front of the roof sensors."""
    v = np.array([[x, y, z] for z in (0.3, 1.45) for x, y in ((-2.3, -0.95), (2.3, -0.95), (2.3, 0.95),
                                                             (-2.3, 0.95))])
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return v, f


def _recorded() -> dict:
    import json

    return json.loads(PINNED_FILE.read_text()) if PINNED_FILE.exists() else {}


def _this_configuration() -> dict:
    from adv3d_runner.machine import numerical_config

    return numerical_config()


FRAMES = ("hdl64-frame0", "hdl64-frame20", "hdl64-frame40", "hdl64-frame10-ideal", "two-sensors-ego-body-frame5",
          "cache-miss-frame0", "cache-miss-frame30", "cache-hit-frame0", "cache-hit-frame30")


def test_frames_are_pinned_to_their_bytes():
    config = _this_configuration()
    recorded = _recorded().get(config["key"])
    if recorded is None:
        pytest.skip(f"no digests recorded for numerical configuration {config['key']} "
                    f"(python -m tests.test_lidar_pinned --record)")
    frames = pinned_frames()
    assert set(frames["two-sensors-ego-body-frame5"].sensor) == {0, 1}
    assert {name: digest(frame) for name, frame in frames.items()} == recorded["digests"]


def test_configurations_on_record_are_whole_and_differ_where_embree_does():
    """Each entry holds its configuration and every frame; configurations whose Embree ISAs
    differ give other frames (else the ISA would not need to be part of the key)."""
    kept = _recorded()
    assert kept, f"{PINNED_FILE} is missing"
    first_frame = {}
    for key, entry in kept.items():
        assert entry["config"]["key"] == key and set(entry["digests"]) == set(FRAMES)
        first_frame.setdefault(entry["config"]["embree_isa"], set()).add(entry["digests"]["hdl64-frame0"])
    if len(first_frame) > 1:
        assert len(set.union(*first_frame.values())) > 1


def _record() -> None:
    import json

    config = _this_configuration()
    frames = pinned_frames()
    kept = _recorded()
    kept[config["key"]] = {"config": config, "digests": {name: digest(frame) for name, frame in frames.items()}}
    PINNED_FILE.write_text(json.dumps(kept, indent=1, sort_keys=True) + "\n")
    print(f"recorded {len(frames)} digests for {config['key']}: {config['cpu']}, Embree {config['embree_isa']}, "
          f"numpy {config['numpy_simd']}")


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python -m tests.test_lidar_pinned --record")
    _record()
