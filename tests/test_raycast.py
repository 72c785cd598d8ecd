"""Embree mesh BVHs and the beam tables: analytic ranges at float32 precision."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from adv3d_runner.errors import ConfigError
from adv3d_runner.sensors.beams import MODELS, generic_model, get_model
from adv3d_runner.sensors.raycast import MeshBVH, cast_nearest, mesh_key

EPS32 = np.finfo(np.float32).eps
# Float32 vertices and directions plus Embree's own float32 arithmetic: a few ulps of the range.
RTOL = 16 * EPS32


def exact_hits(vertices, faces, origin, dirs):
    """Reference nearest hit distance per ray, float64 Moller-Trumbore over all triangles."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces)]
    e1, e2 = v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]
    out = np.full(len(dirs), np.inf)
    for i, d in enumerate(np.asarray(dirs, np.float64)):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - v[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        w = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        if hit.any():
            out[i] = t[hit].min()
    return out


def test_plane_range_float32_precision():
    h = 1.7
    plane_v = np.array([[-500, -500, 0], [500, -500, 0], [500, 500, 0], [-500, 500, 0]], float)
    bvh = MeshBVH(plane_v, np.array([[0, 1, 2], [0, 2, 3]]))
    el = np.deg2rad(np.linspace(-2, -60, 40))
    az = np.linspace(-np.pi, np.pi, 37)
    E, A = np.meshgrid(el, az)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t, prim, normal = cast_nearest(bvh, np.array([[0, 0, h]]), d, 1000.0)
    expected = h / np.sin(-E.reshape(-1))
    assert (prim >= 0).all()
    np.testing.assert_allclose(t, expected, rtol=RTOL)
    # Geometric normal is vertical.
    assert np.allclose(np.abs(normal[:, 2]) / np.linalg.norm(normal, axis=1), 1.0)


def test_sphere_range_float32_precision():
    radius, centre = 2.0, np.array([30.0, -4.0, 1.5])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    bvh = MeshBVH(sphere.vertices + centre, sphere.faces)
    origin = np.array([0.0, 0.0, 1.8])
    # Rays aimed at mesh vertices: the vertex lies exactly on the analytic sphere.
    targets = sphere.vertices + centre
    front = (targets - origin) @ (centre - origin) > 0
    aim = targets - origin
    dist_true = np.linalg.norm(aim, axis=1)
    d = aim / dist_true[:, None]
    t, prim, _ = cast_nearest(bvh, origin[None], d, 200.0)
    visible = front & (np.abs(t - dist_true) < 1e-3)  # silhouette-adjacent vertices may be occluded
    assert visible.sum() > 50
    np.testing.assert_allclose(t[visible], dist_true[visible], rtol=RTOL)
    # Generic rays: equal to the exact float64 intersection of the faceted mesh.
    rng = np.random.default_rng(3)
    dirs = (centre - origin) + rng.uniform(-1.5, 1.5, (200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t, prim, _ = cast_nearest(bvh, origin[None], dirs, 200.0)
    ref = exact_hits(sphere.vertices + centre, sphere.faces, origin, dirs)
    hit = np.isfinite(ref)
    assert hit.sum() > 100 and np.array_equal(prim >= 0, hit)
    np.testing.assert_allclose(t[hit], ref[hit], rtol=RTOL)
    # ... and within the faceting error of the analytic sphere.
    oc = origin - centre
    b = dirs[hit] @ oc
    analytic = -b - np.sqrt(b * b - (oc @ oc - radius ** 2))
    assert np.all(np.abs(t[hit] - analytic) < radius * (1 - np.cos(np.deg2rad(12))))


def test_box_range_known():
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    bvh = MeshBVH(box.vertices + [20.0, 0.0, 1.0], box.faces)
    el = np.deg2rad(np.linspace(-5, 2, 15))
    az = np.deg2rad(np.linspace(-2, 2, 9))
    E, A = np.meshgrid(el, az)
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t, prim, _ = cast_nearest(bvh, np.array([[0, 0, 1.0]]), d, 100.0)
    expected = 19.0 / d[:, 0]  # front face x = 19
    y = expected * d[:, 1]
    z = 1.0 + expected * d[:, 2]
    front = (np.abs(y) < 0.999) & (z > 0.001) & (z < 1.999)
    assert front.sum() > 50
    np.testing.assert_allclose(t[front], expected[front], rtol=RTOL)
    assert (prim[~front & (z < 0)] == -1).all()


def test_tfar_limit_and_in_place_update():
    box = trimesh.creation.box((1, 1, 1))
    bvh = MeshBVH(box.vertices + [10, 0, 0], box.faces)
    d = np.array([[1, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    t = np.array([100, 5, 100], np.float32)
    prim, _ = bvh.intersect(np.zeros((1, 3), np.float32), d, t)
    assert prim[0] >= 0 and abs(t[0] - 9.5) < 1e-5
    assert prim[1] == -1 and t[1] == 5  # the hit lies beyond the limit
    assert prim[2] == -1 and t[2] == 100


def test_empty_mesh_misses_everything():
    bvh = MeshBVH(np.zeros((0, 3)), np.zeros((0, 3), int))
    t, prim, _ = cast_nearest(bvh, np.zeros((1, 3)), np.array([[1.0, 0, 0]]), 50.0)
    assert prim[0] == -1 and t[0] == 50.0


def test_mesh_key_depends_on_content():
    box = trimesh.creation.box((1, 2, 3))
    assert mesh_key(box.vertices, box.faces) == mesh_key(box.vertices.copy(), box.faces.copy())
    assert mesh_key(box.vertices * 1.01, box.faces) != mesh_key(box.vertices, box.faces)


def test_beam_tables():
    hdl = get_model("hdl64")
    assert hdl.beams == 64 and 125_000 <= hdl.rays <= 140_000
    el = np.rad2deg(hdl.elevations)
    assert 1.5 < el.max() < 2.5 and -25.0 < el.min() < -24.0
    vlp = get_model("VLP-32C")
    el = np.sort(np.rad2deg(vlp.elevations))
    assert vlp.beams == 32 and el[0] == pytest.approx(-25) and el[-1] == pytest.approx(15)
    assert np.ptp(np.diff(el)) > 1.0  # non-uniform spacing
    assert get_model("os1-128").beams == 128
    assert get_model("generic-8").beams == 8
    assert get_model("hdl64", columns=100).rays == 6400
    for model in MODELS.values():
        d, ring, az = model.ray_table()
        assert d.shape == (model.rays, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)
        assert ring.min() == 0 and ring.max() == model.beams - 1
        assert model.max_range > 0 and model.range_noise > 0 and 0 < model.ray_drop < 0.2
    # ring 0 is the lowest laser
    d, ring, _ = vlp.ray_table()
    assert d[ring == 0, 2].max() < d[ring == vlp.beams - 1, 2].min()


def test_bad_models_raise():
    with pytest.raises(ConfigError):
        get_model("hdl65")
    with pytest.raises(ConfigError):
        generic_model(0)
    with pytest.raises(ConfigError):
        get_model("generic-8", max_range=-1)
