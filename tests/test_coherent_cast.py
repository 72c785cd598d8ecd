"""Coherent casts with certificates (sensors/coherent.py) give the reference hits bit for bit.

(test_raycast.py's ray sets run on coherent meshes too: test_direct_cast_equals_embreex_bit_for_bit.)"""
import numpy as np
import pytest

from adv3d_runner.sensors import coherent
from adv3d_runner.sensors.raycast import MeshBVH
from tests.test_raycast import _embreex_cast, _same_bits, meshes, same_isa_as_embreex  # noqa: F401 (fixture)

pytestmark = pytest.mark.skipif(not __import__("adv3d_runner.sensors.embree", fromlist=["available"]).available(),
                                reason="the direct Embree binding is unavailable")


def _grid(x0, x1, y0, y1, nx, ny, z=0.0):
    """A flat rectangle (z) of nx x ny squares, two triangles each: (V, 3), (F, 3)."""
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    idx = np.arange(gx.size).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _two_layers(gap):
    """A road grid and a second, differently tessellated grid ``gap`` above it (0: coplanar)."""
    v1, f1 = _grid(-60, 60, -20, 20, 12, 4)
    v2, f2 = _grid(-55, 65, -18, 22, 7, 3, z=gap)
    return (np.concatenate([v1, v2]).astype(np.float32),
            np.concatenate([f1, f2 + len(v1)]).astype(np.int32))


def _lidar_rays():
    from adv3d_runner.sensors.lidar import MountedLidar

    return np.ascontiguousarray(MountedLidar("hdl64", (0, 0, 1.73, 0, 0, 0)).dirs, np.float32)


def _cast(bvh, o, d, limit=120.0, coherent_query=False):
    t = np.full(len(d), limit, np.float32)
    if coherent_query:  # Embree's coherent query without certificates
        return t, bvh._scene.intersect(o, d, t, coherent=True)
    return t, bvh.intersect(o, d, t)[0]


def test_certified_cast_equals_the_reference_where_faces_tie():
    """Two coplanar tessellations of one road: every hit ties. With AVX-512 Embree's coherent
    query reports the other face on a good part of the rays (why certificates exist); with AVX2
    and SSE4.2 it happens to agree with the reference query on this layout. Every face is
    crowded, so the certified cast casts them all again and equals the reference on any ISA."""
    from adv3d_runner.sensors import embree

    v, f = _two_layers(0.0)
    plain, coh = MeshBVH(v, f), MeshBVH(v, f, coherent=True)
    assert coh.certificates is not None and coh.certificates.crowded.all()
    d, o = _lidar_rays(), np.array([[0.3, 0.2, 1.73]], np.float32)
    t_ref, p_ref = _cast(plain, o, d)
    t_raw, p_raw = _cast(plain, o, d, coherent_query=True)
    if embree.isa() == "avx512":
        assert (p_raw != p_ref).sum() > 1000  # the certificate is needed
    t_new, p_new = _cast(coh, o, d)
    assert _same_bits(t_new, t_ref) and np.array_equal(p_new, p_ref)


def test_certified_hits_are_kept_where_no_face_competes():
    """A second layer 1 cm above the road (like a lane marking) competes with nothing at a 2 mm
    margin: most hits keep their coherent result, and every ray equals the reference."""
    v, f = _two_layers(0.01)
    plain, coh = MeshBVH(v, f), MeshBVH(v, f, coherent=True)
    assert not coh.certificates.crowded.any()
    d = _lidar_rays()
    for o in ([0.3, 0.2, 1.73], [-20.0, 5.0, 1.73], [40.0, -3.0, 2.5]):
        o = np.array([o], np.float32)
        before = coh.recast_rays
        t_ref, p_ref = _cast(plain, o, d)
        t_new, p_new = _cast(coh, o, d)
        assert _same_bits(t_new, t_ref) and np.array_equal(p_new, p_ref)
        recast_hits = coh.recast_rays - before - int((p_ref < 0).sum())  # misses are always cast again
        assert recast_hits < 0.1 * (p_ref >= 0).sum()  # near edges and the range limit only


@same_isa_as_embreex
def test_certified_cast_equals_embreex_on_lidar_frames(meshes):  # noqa: F811
    """HDL-64E frames from 25 sensor positions over the highway background, and a strided
    (non-contiguous) limit array."""
    v, f, ref, _ = meshes["background"]
    coh = MeshBVH(v, f, coherent=True)
    d = _lidar_rays()
    rng = np.random.default_rng(3)
    lo, hi = v.min(axis=0), v.max(axis=0)
    kept = 0
    for _ in range(25):
        o = np.array([[rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), rng.uniform(1.5, 2.5)]], np.float32)
        t_ref = np.full(len(d), 120.0, np.float32)
        p_ref = _embreex_cast(ref, o, d, t_ref)
        before = coh.recast_rays
        t_new, p_new = _cast(coh, o, d)
        assert _same_bits(t_new, t_ref) and np.array_equal(p_new, p_ref)
        kept += len(d) - (coh.recast_rays - before)
    assert kept > 0.5 * 25 * 50_000  # the coherent results are mostly used, not all cast again
    t = np.full(2 * len(d), 120.0, np.float32)
    p, _ = coh.intersect(o, d, t[::2])
    assert _same_bits(t[::2], t_ref) and np.array_equal(p, p_ref)


def test_face_certificates():
    m = coherent.MARGIN_M
    # coplanar neighbours sharing an edge: not crowded; a face on top of another: crowded.
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    assert not coherent.face_certificates(v, f).crowded.any()
    v2 = np.concatenate([v, v + [1, 1, 0]])
    f2 = np.concatenate([f, f + 4])
    assert coherent.face_certificates(v2, f2).crowded.all()
    # parallel layers: crowded within the margin, not beyond it
    for gap, expect in ((0.5 * m, True), (3 * m, False)):
        v3 = np.concatenate([v, v + [0.5, 0.5, gap]])
        assert coherent.face_certificates(v3, f2).crowded.all() == expect, gap
    # a face too small for its inner triangle, and a degenerate one
    tiny = np.array([[0, 0, 0], [0.005, 0, 0], [0, 0.005, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], float)
    assert coherent.face_certificates(tiny, np.array([[0, 1, 2], [3, 4, 5]])).crowded.all()
    cert = coherent.face_certificates(v, f)
    assert np.allclose(cert.altitudes[0], [10 / np.sqrt(2), 10, 10]) and np.allclose(cert.normals[0], [0, 0, 1])


def test_separated_never_claims_a_gap_that_points_close_the_triangles_do_not_have():
    """Pairs of random triangles: where two sampled points (one on each) are within the gap,
    the test must not call them separated by more than it."""
    rng = np.random.default_rng(5)
    a = rng.uniform(-1, 1, (4000, 3, 3))
    b = a[:, :1] + rng.uniform(-1, 1, (4000, 3, 3)) * rng.uniform(0.05, 1, (4000, 1, 1)) + rng.normal(0, 0.3, (4000, 1, 3))
    w = rng.dirichlet(np.ones(3), 300)
    pa, pb = np.einsum("sk,pkd->psd", w, a), np.einsum("sk,pkd->psd", w, b)
    close = np.array([np.sqrt(((x[:, None] - y[None]) ** 2).sum(-1)).min() for x, y in zip(pa, pb)])
    gap = 0.05
    sep = coherent.separated(a, b, gap)
    assert not (sep & (close <= gap)).any()
    assert sep.sum() > 500 and (~sep).sum() > 500  # both outcomes occur


def test_uncertain_rays_flags_misses_edges_grazing_rays_and_limits():
    cert = coherent.face_certificates(np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], float), np.array([[0, 1, 2]]))
    prim = np.array([-1, 0, 0, 0, 0], np.int32)
    limit = np.full(5, 50.0, np.float32)
    t = np.array([50.0, 20.0, 20.0, 49.999, 20.0], np.float32)
    uv = np.array([[0, 0], [0.3, 0.3], [0.0001, 0.5], [0.3, 0.3], [0.3, 0.3]], np.float32)
    dirs = np.array([[0, 0, -1]] * 4 + [[1, 0, -0.001]], np.float32)
    redo = coherent.uncertain_rays(prim, t, uv, dirs, limit, cert.crowded, cert.altitudes, cert.normals,
                                   cert.cell_slot, cert.cell_frame, cert.cell_crowded, cert.margin,
                                   coherent.MIN_SIN_INCIDENCE)
    assert redo.tolist() == [0, 2, 3, 4]  # a miss, near an edge, near the limit, grazing


def test_cells_index_the_points_they_hold():
    """cell_index of a point inside the triangle names a cell whose corners hold it."""
    corners, exists = coherent.cell_corners()
    rng = np.random.default_rng(2)
    w = rng.dirichlet(np.ones(3), 5000)
    for (u, v) in w[:, 1:]:
        c = coherent.cell_index(u, v)
        assert c < len(exists) and exists[c]
        # barycentric of (u, v) in the cell's corner triangle (in the (u, v) plane)
        a, b, d = corners[c][:, 1:]
        m = np.array([b - a, d - a]).T
        s, t = np.linalg.solve(m, np.array([u, v]) - a)
        assert s >= -1e-9 and t >= -1e-9 and s + t <= 1 + 1e-9
    assert coherent.cell_index(-0.01, 0.5) == coherent.cell_index(0.6, 0.5) == len(exists)  # outside


def test_only_the_cells_a_patch_overlaps_are_cast_again():
    """A road of two big faces with a small coplanar patch over one corner: both road faces are
    crowded, but only the cells near the patch; most hits keep the coherent result, and every ray
    equals the reference."""
    v1, f1 = _grid(-60, 60, -20, 20, 1, 1)
    v2, f2 = _grid(-58, -52, -18, -12, 1, 1)
    v = np.concatenate([v1, v2]).astype(np.float32)
    f = np.concatenate([f1, f2 + len(v1)]).astype(np.int32)
    plain, coh = MeshBVH(v, f), MeshBVH(v, f, coherent=True)
    cert = coh.certificates
    assert cert.crowded[:2].all() and (cert.cell_slot[:2] >= 0).all()
    table = cert.cell_crowded[cert.cell_slot[:2], :-1][:, coherent.cell_corners()[1]]
    assert 0 < table.sum() < 0.5 * table.size  # some cells, not most
    d, o = _lidar_rays(), np.array([[10.0, 5.0, 1.73]], np.float32)
    t_ref, p_ref = _cast(plain, o, d)
    t_new, p_new = _cast(coh, o, d)
    assert _same_bits(t_new, t_ref) and np.array_equal(p_new, p_ref)
    recast_hits = coh.recast_rays - int((p_ref < 0).sum())
    assert recast_hits < 0.2 * (p_ref >= 0).sum()


def test_candidate_pairs_in_chunks_equal_one_sweep(monkeypatch):
    rng = np.random.default_rng(4)
    lo = rng.uniform(0, 100, (400, 3)) * [1.0, 0.2, 0.05]  # a road-like strip: long in x
    hi = lo + rng.uniform(0, 8, (400, 3))
    i, j = coherent.candidate_pairs(lo, hi, 0.5)
    monkeypatch.setattr(coherent, "_CHUNK_PAIRS", 7)
    i2, j2 = coherent.candidate_pairs(lo, hi, 0.5)
    assert len(i) > 100
    assert sorted(zip(i.tolist(), j.tolist())) == sorted(zip(i2.tolist(), j2.tolist()))
    brute = {(a, b) for a in range(400) for b in range(a + 1, 400)
             if np.all(lo[a] <= hi[b] + 0.5) and np.all(lo[b] <= hi[a] + 0.5)}
    assert {tuple(sorted(p)) for p in zip(i.tolist(), j.tolist())} == brute


def test_a_mesh_of_long_overlapping_strips_is_cast_plainly(monkeypatch):
    """Past MAX_SWEEP_PAIRS x-overlaps the mesh gets no certificates and the reference query."""
    v, f = _two_layers(0.01)
    monkeypatch.setattr(coherent, "MAX_SWEEP_PAIRS", 10)
    coh = MeshBVH(v, f, coherent=True)
    assert coh.certificates is None
    d, o = _lidar_rays(), np.array([[0.3, 0.2, 1.73]], np.float32)
    t_ref, p_ref = _cast(MeshBVH(v, f), o, d)
    t_new, p_new = _cast(coh, o, d)
    assert _same_bits(t_new, t_ref) and np.array_equal(p_new, p_ref)
