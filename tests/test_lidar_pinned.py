"""The LiDAR pipeline's output pinned to its bytes: sha256 of every frame array for a fixed
scene, rig and seed. Written before the pipeline was sped up (issue 16, point 2), so any
optimisation that changes one bit of a point, a label or a random draw fails here.

The digests were taken on this project's machine (x86-64, numpy 1.26.4, embreex 4.4.0.post1);
numpy's float32 exp and Embree's traversal may round differently on other CPUs or versions.
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

PINNED = {
    "hdl64-frame0": "548cbef5cd2909c8c9796548dcfb8cc04b2b87a0f4ed947b901695fb46867531",  # 106836 points
    "hdl64-frame20": "7ff80ff2412743e86fa871d425af119c3fd47b3cb09028ac7bed76b975babfb0",  # 106805 points
    "hdl64-frame40": "5500265e226a8b2f9b544905a89a62291e6994dcd4441106e1f81130a68769f1",  # 106883 points
    "hdl64-frame10-ideal": "4d13459fd09ff2f7dbd76383c1c5608f6f726b475d9b529622cfcf18c28286af",  # 109068 points
    "two-sensors-ego-body-frame5": "0ea04388534c757ca213b80ff22f185c8d12d44900f8860702cba818fe4a710a",  # 54055 points
    "cache-miss-frame0": "b40cff88f77b9ef75d00e6aaec844baf43f757e0f841864b4b23b6a38ee025d9",  # 107022 points
    "cache-miss-frame30": "89e483996a6b74ed0e757f0062813fb686b5b2aa531b8881d114a8e871743ec4",  # 106976 points
    "cache-hit-frame0": "b40cff88f77b9ef75d00e6aaec844baf43f757e0f841864b4b23b6a38ee025d9",  # 107022 points
    "cache-hit-frame30": "89e483996a6b74ed0e757f0062813fb686b5b2aa531b8881d114a8e871743ec4",  # 106976 points
}


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


def _pinned_platform() -> bool:
    """The digests hold where they were taken: x86-64 with the pinned numpy and embreex."""
    import platform
    from importlib.metadata import version

    return (platform.machine() in ("x86_64", "AMD64") and np.__version__ == "1.26.4"
            and version("embreex") == "4.4.0.post1")


@pytest.mark.skipif(not _pinned_platform(), reason="digests taken on x86-64, numpy 1.26.4, embreex 4.4.0.post1")
def test_frames_are_pinned_to_their_bytes():
    frames = pinned_frames()
    assert set(frames["two-sensors-ego-body-frame5"].sensor) == {0, 1}
    assert {name: digest(frame) for name, frame in frames.items()} == PINNED


if __name__ == "__main__":  # prints the table to paste above
    for name, frame in pinned_frames().items():
        print(f'    "{name}": "{digest(frame)}",  # {len(frame)} points')
