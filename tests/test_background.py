"""Background geometry and actor asset assignment."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.scene import background as bgm
from adv3d_runner.scene.actors import actor_mesh, assign_assets, choose_asset
from adv3d_runner.scene.generate import generate_scene
from adv3d_runner.scene.schema import Background, Lane, load_scene

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def scene():
    return generate_scene(2, layout="onramp", density="light")


def test_background_mesh_is_valid_and_has_every_surface(scene):
    v, f, k = bgm.background_mesh(scene)
    assert v.dtype == np.float64 and v.shape[1] == 3
    assert f.dtype == np.int32 and f.shape[1] == 3 and k.dtype == np.int8
    assert len(f) == len(k) and f.min() >= 0 and f.max() < len(v)
    assert np.isfinite(v).all()
    kinds = set(np.unique(k).tolist())
    assert {bgm.ASPHALT, bgm.LANE_PAINT, bgm.CONCRETE, bgm.GROUND} <= kinds
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert np.all(area > 0)
    assert len(f) < 50_000  # modest: one Embree scene per scene
    # road at z=0, paint a few mm above, ground below, barriers up to their height
    assert np.allclose(v[f[k == bgm.ASPHALT]][..., 2], 0.0)
    assert np.allclose(v[f[k == bgm.LANE_PAINT]][..., 2], bgm.MARKING_Z)
    assert np.all(v[f[k == bgm.GROUND]][..., 2] < 0)
    assert v[f[k == bgm.CONCRETE]][..., 2].max() == pytest.approx(0.81)
    refl = bgm.reflectivity(k)
    assert refl.shape == k.shape and np.all((refl > 0) & (refl <= 1))
    assert bgm.REFLECTIVITY[bgm.LANE_PAINT] > bgm.REFLECTIVITY[bgm.ASPHALT]


def test_road_covers_the_ego_path(scene):
    """Every ego position lies on asphalt (point-in-triangle on the road faces)."""
    v, f, k = bgm.background_mesh(scene)
    tri = v[f[k == bgm.ASPHALT]][..., :2]
    pts = scene.ego_poses()[::20, :2]
    for p in pts:
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        def cross(o, u, w):
            return (u[:, 0] - o[:, 0]) * (w[1] - o[:, 1]) - (u[:, 1] - o[:, 1]) * (w[0] - o[:, 0])
        d1, d2, d3 = cross(a, b, p), cross(b, c, p), cross(c, a, p)
        inside = ((d1 >= 0) & (d2 >= 0) & (d3 >= 0)) | ((d1 <= 0) & (d2 <= 0) & (d3 <= 0))
        assert inside.any()


def test_degenerate_lanes_do_not_break_background(scene):
    scene = copy.deepcopy(scene)
    scene.lanes.append(Lane(999, [[0, 0], [0, 0]], 3.5))  # collapses to a point
    scene.lanes.append(Lane(998, [[0, 50], [0, 50], [10, 50], [10, 50]], 3.5))
    scene.background = Background(0.0, 0.0, 0.0, False)
    v, f, k = bgm.background_mesh(scene)
    assert np.isfinite(v).all() and len(f) > 0


def test_real_scene_background():
    scene = load_scene(REPO / "scenes" / "real" / "USA_US101-4_1_T-1.json.gz")
    v, f, k = bgm.background_mesh(scene)
    assert np.isfinite(v).all() and (k == bgm.ASPHALT).sum() > 100


class _Asset:
    def __init__(self, id, cls, dims):
        self.id, self.vehicle_class, self.dimensions = id, cls, tuple(dims)


class _Library:
    def __init__(self, assets):
        self.assets = assets
        self.root = "fake"

    def by_class(self, cls):
        return [a for a in self.assets if a.vehicle_class == cls]

    def ids(self):
        return [a.id for a in self.assets]


def test_nearest_size_rule_by_class_and_closest_dimensions(scene):
    """The rule of shape space v1 (kept to record the shipped scenes' meshes)."""
    lib = _Library([_Asset("z-small", "sedan", (4.2, 1.7, 1.4)), _Asset("a-big", "sedan", (5.2, 1.9, 1.5)),
                    _Asset("suv1", "suv", (4.8, 1.95, 1.75)), _Asset("tr", "truck", (14, 2.5, 3.9))])
    near = "nearest-size"
    assert choose_asset(lib, "sedan", np.array([4.3, 1.7, 1.4]), rule=near) == "z-small"
    assert choose_asset(lib, "sedan", np.array([5.0, 1.9, 1.5]), rule=near) == "a-big"
    assert choose_asset(lib, "pickup", np.array([5.5, 2.0, 1.9]), rule=near) == "suv1"  # fallback class
    assert choose_asset(lib, "bus", np.array([12, 2.5, 3.2]), rule=near) == "tr"
    assert choose_asset(_Library([]), "sedan", np.ones(3), rule=near) is None
    # order of the library does not matter
    rev = _Library(lib.assets[::-1])
    out1, out2 = assign_assets(scene, lib, rule=near), assign_assets(scene, rev, rule=near)
    assert [a.asset for a in out1.actors] == [a.asset for a in out2.actors]
    assert all(a.asset is not None for a in out1.actors)
    assert all(a.asset is None for a in scene.actors)  # input untouched


def test_draw_rule_uses_every_asset_of_the_class_seeded_by_scene_and_actor():
    from collections import Counter

    from adv3d_runner.errors import ConfigError

    sedans = [_Asset(f"sedan-{i}", "sedan", (4.2 + 0.1 * i, 1.8, 1.45)) for i in range(6)]
    lib = _Library(sedans + [_Asset("suv1", "suv", (4.8, 1.95, 1.75))])
    keys = [f"scene-{s}/{a}" for s in range(40) for a in range(1, 26)]
    picks = [choose_asset(lib, "sedan", key=k) for k in keys]
    counts = Counter(picks)
    assert set(counts) == {a.id for a in sedans}  # every sedan appears, no suv
    assert max(counts.values()) < 2.0 * len(keys) / len(sedans)  # roughly uniform
    assert picks == [choose_asset(_Library(lib.assets[::-1]), "sedan", key=k) for k in keys]  # order-free
    assert choose_asset(lib, "pickup", key="s/1") == "suv1"  # fallback class
    # adding an asset changes only the actors the new asset wins
    grown = _Library(lib.assets + [_Asset("sedan-new", "sedan", (4.5, 1.8, 1.45))])
    after = [choose_asset(grown, "sedan", key=k) for k in keys]
    changed = [(a, b) for a, b in zip(picks, after) if a != b]
    assert changed and all(b == "sedan-new" for _, b in changed)
    assert len(changed) < 2.0 * len(keys) / 7
    with pytest.raises(ConfigError, match="key"):
        choose_asset(lib, "sedan")
    with pytest.raises(ConfigError, match="rule"):
        choose_asset(lib, "sedan", key="a/1", rule="closest")


def test_recorded_assets_are_kept_and_checked(scene):
    from adv3d_runner.errors import ConfigError

    lib = _Library([_Asset("s1", "sedan", (4.5, 1.8, 1.45)), _Asset("s2", "sedan", (4.6, 1.8, 1.45)),
                    _Asset("suv1", "suv", (4.8, 1.95, 1.75)), _Asset("tr", "truck", (14, 2.5, 3.9)),
                    _Asset("v1", "van", (5.2, 2.0, 2.1)), _Asset("p1", "pickup", (5.5, 2.0, 1.9))])
    drawn = assign_assets(scene, lib)
    keys = [f"{scene.id}/{a.id}" for a in scene.actors]
    assert [a.asset for a in drawn.actors] == [choose_asset(lib, a.cls, key=k) for a, k in zip(scene.actors, keys)]
    pinned = assign_assets(scene, lib)
    pinned.actors[0].asset = "s2" if pinned.actors[0].asset != "s2" else "s1"
    again = assign_assets(pinned, lib)  # a recorded asset stays
    assert again.actors[0].asset == pinned.actors[0].asset
    pinned.actors[0].asset = "gone"
    with pytest.raises(ConfigError, match=r"actor .* uses asset 'gone'"):
        assign_assets(pinned, lib)


def test_actor_mesh_fits_box(tmp_path):
    from adv3d_runner.shapes import library as L
    try:
        lib = L.load_library()
    except Exception:
        pytest.skip("vehicle library not available")
    if not lib.assets:
        pytest.skip("empty vehicle library")
    asset = sorted(lib.assets, key=lambda a: a.id)[0]
    mesh = actor_mesh(lib, asset.id, np.array([4.5, 1.8, 1.5]))
    np.testing.assert_allclose(mesh.bounds, [[-2.25, -0.9, 0.0], [2.25, 0.9, 1.5]], atol=1e-9)
    used = mesh.vertices[np.unique(mesh.faces)]
    np.testing.assert_array_equal(mesh.bounds, [used.min(axis=0), used.max(axis=0)])


def test_generated_scenes_record_drawn_assets_and_keep_them(tmp_path):
    """`scenes generate` records the drawn asset per actor; `assign-assets` keeps what is
    recorded unless told to overwrite."""
    from adv3d_runner.cli import main
    from adv3d_runner.shapes.library import load_library

    lib = load_library()
    assert main(["-q", "scenes", "generate", "--out", str(tmp_path), "--count", "2"]) == 0
    files = sorted(tmp_path.glob("*.json.gz"))
    scenes = [load_scene(f) for f in files]
    for s in scenes:
        assert all(a.asset in lib.ids() for a in s.actors)
        assert [a.asset for a in s.actors] == [choose_asset(lib, a.cls, key=f"{s.id}/{a.id}") for a in s.actors]
    before = [f.read_bytes() for f in files]
    assert main(["-q", "scenes", "assign-assets", str(tmp_path), "--rule", "nearest-size"]) == 0
    assert [f.read_bytes() for f in files] == before  # recorded assets are kept
    assert main(["-q", "scenes", "assign-assets", str(tmp_path), "--rule", "nearest-size", "--overwrite"]) == 0
    assert [f.read_bytes() for f in files] != before


def test_shipped_scenes_record_the_meshes_they_were_simulated_with():
    """The benchmark and real scenes record the v1 (nearest-size) assignment, so the library's
    growth does not change them (docs/scenes.md); every recorded asset is in the library."""
    from adv3d_runner.shapes.library import load_library

    lib = load_library()
    for path in sorted((REPO / "scenes").rglob("*.json.gz"))[::10]:
        scene = load_scene(path)
        assert all(a.asset in lib.ids() for a in scene.actors), path
