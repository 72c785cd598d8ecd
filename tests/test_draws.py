"""The compiled LiDAR draws (sensors/draws.py) are numpy's PCG64 float32 draws, bit for bit."""
import numpy as np
import pytest

from adv3d_runner.sensors import draws
from adv3d_runner.sensors.beams import get_model
from adv3d_runner.sensors.lidar import LidarRig, MountedLidar, simulate_frame
from tests.test_lidar import EGO, assert_frames_equal, crowded_world_and_poses


def _numpy_draws(rng, n_gauss, n_uniform):
    return rng.standard_normal(n_gauss, dtype=np.float32), rng.random(n_uniform, dtype=np.float32)


def _same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def test_the_compiled_draws_are_in_use_here():
    # The pinned numpy (1.26) and numba (0.60-0.61): the self-check against numpy passes, so the
    # frames take the compiled path (a failure here means every frame falls back to numpy).
    assert draws.compiled_draws_available()


@pytest.mark.parametrize("seed", [0, 1, 7, 2024, 987654321])
def test_draws_equal_numpy_across_sizes_and_interleavings(seed):
    ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
    sizes = np.random.default_rng(seed + 1).integers(0, 60_000, size=(12, 2))
    sizes[3] = (0, 5)        # uniforms only
    sizes[4] = (7, 0)        # normals only
    sizes[5] = (0, 0)
    for n_gauss, n_uniform in sizes:
        g, u = draws.draw_f32(ours, int(n_gauss), int(n_uniform))
        g_ref, u_ref = _numpy_draws(ref, int(n_gauss), int(n_uniform))
        assert _same(g, g_ref) and _same(u, u_ref)
        assert ours.bit_generator.state == ref.bit_generator.state
        # other draws in between (an odd count leaves a buffered half word for the next call)
        assert ours.integers(0, 1000) == ref.integers(0, 1000)
        np.testing.assert_array_equal(ours.random(3, dtype=np.float32), ref.random(3, dtype=np.float32))


def test_rare_ziggurat_paths_are_exercised_and_equal():
    ours, ref = np.random.default_rng(11), np.random.default_rng(11)
    g, _ = draws.draw_f32(ours, 1_000_000, 0)
    g_ref = ref.standard_normal(1_000_000, dtype=np.float32)
    assert _same(g, g_ref)
    # |x| beyond the ziggurat's base r (3.654) only comes from the tail path; the wedges
    # (about 0.7 % of draws) consume an extra word, which the equal states after show
    assert (np.abs(g) > draws._TABLES[3]).sum() > 50
    assert ours.bit_generator.state == ref.bit_generator.state


def test_other_bit_generators_use_numpy():
    for bg in (np.random.Philox(3), np.random.MT19937(3), np.random.SFC64(3)):
        ours, ref = np.random.Generator(bg), np.random.Generator(type(bg)(3))
        g, u = draws.draw_f32(ours, 1000, 1000)
        g_ref, u_ref = _numpy_draws(ref, 1000, 1000)
        assert _same(g, g_ref) and _same(u, u_ref)


def test_failed_self_check_falls_back_to_numpy(monkeypatch):
    monkeypatch.setattr(draws, "_checked", False)
    ours, ref = np.random.default_rng(5), np.random.default_rng(5)
    called = []
    monkeypatch.setattr(draws, "_compiled", lambda *a: called.append(a))
    g, u = draws.draw_f32(ours, 100, 100)
    assert not called and _same(g, ref.standard_normal(100, dtype=np.float32))


def test_lidar_frames_equal_the_numpy_draws(monkeypatch):
    """A noisy, dropping rig over a crowded scene: the same frame with the numpy calls."""
    world, poses = crowded_world_and_poses(EGO)
    rig = LidarRig([MountedLidar(get_model("hdl64", columns=600), (0.0, 0.0, 1.73, 0.0, 0.0, 0.0)),
                    MountedLidar(get_model("vlp32c", columns=400), (1.2, 0.3, 1.5, 0.0, 0.0, 0.4))],
                   ego_dimensions=(4.6, 1.9, 1.5))
    assert rig.sensors[0].model.range_noise > 0 and rig.sensors[0].model.ray_drop > 0
    rng = np.random.default_rng(9)
    frames = [simulate_frame(world, rig, EGO, poses, rng) for _ in range(3)]
    monkeypatch.setattr(draws, "_checked", False)  # numpy's own calls
    rng = np.random.default_rng(9)
    for frame in frames:
        assert_frames_equal(frame, simulate_frame(world, rig, EGO, poses, rng))
