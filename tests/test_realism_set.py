"""Set-level realism (adv3d_runner/shapes/realism_set.py): PointFlow's MMD, COV and 1-NNA with the
Chamfer distance, on cases small enough to compute by hand, and the set JSD as a distance."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import jensenshannon

from adv3d_runner.errors import ConfigError
from adv3d_runner.shapes import realism_set as rs


def test_pointflow_chamfer_is_mean_squared_both_ways():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.0, 0, 0], [3.0, 0, 0]])
    # a -> b: 0 and 1 (1^2) -> mean 0.5; b -> a: 0 and 2^2 -> mean 2
    assert rs.pointflow_chamfer(a, b) == pytest.approx(2.5)
    assert rs.pointflow_chamfer(b, a) == pytest.approx(2.5)
    assert rs.pointflow_chamfer(a, a) == 0.0


def test_mmd_cov_1nna_by_hand():
    # found G = {g0, g1}, reference R = {r0, r1, r2}
    d_gr = np.array([[1.0, 4.0, 9.0],
                     [2.0, 3.0, 8.0]])
    d_gg = np.array([[0.0, 5.0], [5.0, 0.0]])
    d_rr = np.array([[0.0, 6.0, 7.0], [6.0, 0.0, 0.5], [7.0, 0.5, 0.0]])
    m = rs.mmd_cov_1nna(d_gr, d_gg, d_rr)
    # MMD: per reference the closest found: r0 1, r1 3, r2 8 -> mean 4
    assert m["mmd"] == pytest.approx(4.0)
    # COV: g0 -> r0, g1 -> r0: one of three reference shapes covered
    assert m["cov"] == pytest.approx(1 / 3)
    # 1-NN: g0 -> r0 (1 < 5): wrong; g1 -> r0 (2): wrong; r0 -> g0 (1): wrong;
    # r1 -> r2 (0.5): right; r2 -> r1: right  => 2 of 5
    assert m["nna"] == pytest.approx(0.4)


def test_identical_sets_cover_everything_and_separated_sets_are_told_apart():
    rng = np.random.default_rng(0)
    # four small clouds 0.8 m apart along y, at x = -2 m (inside the 8 m BEV window)
    ref = [0.05 * rng.normal(size=(50, 3)) + [-2.0, 0.8 * i - 1.2, 0.0] for i in range(4)]
    same = rs.set_realism([r.copy() for r in ref], ref)
    assert same["mmd_cd_m2"] == pytest.approx(0.0)
    assert same["cov_cd"] == pytest.approx(1.0)
    assert same["jsd_distance"] == pytest.approx(0.0)
    far = rs.set_realism([r + [4.0, 0.0, 0.0] for r in ref], ref)
    assert far["nna_cd"] == pytest.approx(1.0)
    assert far["cov_cd"] == pytest.approx(1.0)  # each far shape's nearest is its own unshifted one
    assert far["jsd_distance"] == pytest.approx(np.sqrt(np.log(2)))  # disjoint: the distance's maximum


def test_set_jsd_is_the_distance_not_the_divergence():
    rng = np.random.default_rng(1)
    found = [rng.normal(size=(300, 3)) for _ in range(3)]
    ref = [rng.normal(loc=0.5, size=(300, 3)) for _ in range(3)]
    from adv3d_runner.shapes.realism import bev_histogram

    p = sum(bev_histogram(x) for x in found).ravel()
    q = sum(bev_histogram(x) for x in ref).ravel()
    got = rs.set_realism(found, ref)["jsd_distance"]
    assert got == pytest.approx(jensenshannon(p, q))  # sqrt of the divergence in nats
    assert got ** 2 < got  # the divergence is the square, smaller below 1


def test_set_realism_refuses_empty_sets():
    with pytest.raises(ConfigError, match="at least one found shape"):
        rs.set_realism([], [np.zeros((3, 3)), np.ones((3, 3))])
