"""Embree mesh BVHs and the beam tables: analytic ranges at float32 precision."""
from __future__ import annotations

from pathlib import Path

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
    # The rays as cast (float32) pass a vertex only within rounding: where the surface grazes
    # the ray, that can land on a neighbouring face a fraction of a mm off (Embree's SSE4.2
    # kernels do on 2 of these rays). Where the ray meets the surface at under 60 degrees from
    # its normal, the hit is the vertex's own distance to a few ulps on every ISA.
    normal = sphere.vertices / radius
    head_on = visible & (np.abs(np.einsum("ij,ij->i", d, normal)) > 0.5)
    assert head_on.sum() > 50
    np.testing.assert_allclose(t[head_on], dist_true[head_on], rtol=RTOL)
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


# -- the direct Embree binding (sensors/embree.py) against embreex's own cast -------------------

def _isa_as_embreex() -> bool:
    """Whether adv3d's Embree device runs the ISA embreex's own device does: embreex's takes no
    configuration and runs Embree's choice (the CPU's best), while ADV3D_EMBREE_ISA may ask
    for a lower one (an emulated CPU, docs/reliability.md), which can round hits differently."""
    from adv3d_runner import machine
    from adv3d_runner.sensors import embree

    return not embree.available() or embree.isa() == machine.embree_native_isa()


#: The direct binding against embreex's own cast, bit for bit: only on the same ISA.
same_isa_as_embreex = pytest.mark.skipif(not _isa_as_embreex(), reason="ADV3D_EMBREE_ISA differs from the ISA "
                                         "embreex's unconfigurable device runs")


def _embreex_cast(scene, origins, dirs, tfar):
    """embreex's ``EmbreeScene.run(..., output=1)``: (N,) int32 faces, ``tfar`` in place."""
    o = np.broadcast_to(origins, dirs.shape) if len(origins) == 1 else origins
    return scene.run(o, dirs, dists=tfar, output=1)["primID"]


def _same_bits(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


@pytest.fixture(scope="module")
def meshes():
    """name -> (vertices float32, faces int32, embreex scene, direct MeshBVH): the first highway
    scene's background (centred as LidarWorld does) and three library vehicles."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    from adv3d_runner.scene.actors import actor_mesh, choose_asset
    from adv3d_runner.scene.background import background_mesh
    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.shapes.library import load_library

    repo_root = Path(__file__).resolve().parent.parent
    path = repo_root / "scenes/highway/highway-benchmark-000000.json.gz"
    scene = load_scene(path)
    v, f, _ = background_mesh(scene, scene_dir=path.parent)
    centre = np.zeros(3)
    centre[:2] = 0.5 * (v[:, :2].min(axis=0) + v[:, :2].max(axis=0))
    out = {"background": (v - centre, f)}
    library = load_library(repo_root / "assets/vehicles/library.json")
    for cls, dims in (("sedan", (4.6, 1.85, 1.5)), ("suv", (4.9, 1.95, 1.8)), ("truck", (9.0, 2.5, 3.4))):
        mesh = actor_mesh(library, choose_asset(library, cls, np.array(dims), rule="nearest-size"), np.array(dims))
        out[cls] = (np.asarray(mesh.vertices), np.asarray(mesh.faces))
    built = {}
    for name, (v, f) in out.items():
        v32, f32 = np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.int32)
        ref = rtcs.EmbreeScene()
        TriangleMesh(ref, v32, f32)
        bvh = MeshBVH(v32, f32)
        assert bvh.direct  # the binding is what the LiDAR uses here (see test_direct_binding_found)
        built[name] = (v32, f32, ref, bvh)
    return built


def _ray_sets(v, f, rng):
    """name -> (origins (1 or N, 3), directions (N, 3), tfar (N,)), all float32."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = np.maximum(hi - lo, 1.0)
    sets = {}
    # Random origins around the mesh, random directions (upward ones miss), N not a multiple of 8.
    n = 10007
    o = (lo - 0.2 * span + rng.random((n, 3)) * 1.4 * span).astype(np.float32)
    d = rng.standard_normal((n, 3)).astype(np.float32)
    sets["random"] = (o, d, np.full(n, 1e4, np.float32))
    # One origin for all (broadcast (1, 3)): a sensor above the mesh's middle, aimed at its
    # vertices exactly (unnormalised directions) and at points of its edges.
    eye = (0.5 * (lo + hi) + [0.3 * span[0], 0.1 * span[1], 0.5 * span[2] + 1.7]).astype(np.float32)[None]
    pick = rng.choice(len(v), min(len(v), 4001), replace=False)
    sets["vertices"] = (eye, v[pick] - eye, np.full(len(pick), 1e4, np.float32))
    fk = f[rng.choice(len(f), min(len(f), 3001), replace=False)]
    a, b = v[fk[:, 0]], v[fk[:, 1]]
    s = rng.choice(np.array([0.5, 0.25, 1 / 3, 0.0, 1.0], np.float32), (len(fk), 1))
    target = (a + s * (b - a)).astype(np.float32)
    sets["edges"] = (eye, target - eye, np.full(len(fk), 1e4, np.float32))
    # Grazing: rays along an edge's own line, from behind its first vertex (per-ray origins).
    o = (a - 0.5 * (b - a)).astype(np.float32)
    sets["along edges"] = (o, (b - a).astype(np.float32), np.full(len(fk), 1e4, np.float32))
    # Grazing: rays in the plane of a face, towards its centroid, from outside the face.
    c = v[fk].mean(axis=1, dtype=np.float64).astype(np.float32)
    o = (c + 1.5 * (a - c)).astype(np.float32)
    sets["in plane"] = (o, c - o, np.full(len(fk), 1e4, np.float32))
    return sets


def _cast_both(ref, bvh, origins, dirs, tfar):
    t_ref, t_dir = tfar.copy(), tfar.copy()
    p_ref = _embreex_cast(ref, origins, dirs, t_ref)
    p_dir, normals = bvh.intersect(origins, dirs, t_dir)
    assert normals is None
    return (t_ref, p_ref), (t_dir, p_dir)


@same_isa_as_embreex
@pytest.mark.parametrize("coherent", [False, True])
@pytest.mark.parametrize("name", ["background", "sedan", "suv", "truck"])
def test_direct_cast_equals_embreex_bit_for_bit(meshes, name, coherent):
    """Also for a coherent mesh (sensors/coherent.py: Embree's coherent query, certified)."""
    v, f, ref, bvh = meshes[name]
    if coherent:
        bvh = MeshBVH(v, f, coherent=True)
    rng = np.random.default_rng(7)
    hits = misses = 0
    for what, (o, d, tfar) in _ray_sets(v, f, rng).items():
        (t_ref, p_ref), (t_dir, p_dir) = _cast_both(ref, bvh, o, d, tfar)
        assert _same_bits(t_dir, t_ref), (name, what, int((t_dir != t_ref).sum()))
        assert np.array_equal(p_dir, p_ref) and p_dir.dtype == np.int32, (name, what)
        hits, misses = hits + int((p_ref >= 0).sum()), misses + int((p_ref < 0).sum())
        # Limits that cut hits: at the hit distance itself, one ulp either side, half of it, random.
        hit = p_ref >= 0
        if hit.sum() < 10:
            continue
        t_hit = t_ref[hit]
        oh = o if len(o) == 1 else o[hit]
        for limit in (t_hit, np.nextafter(t_hit, np.float32(0)), np.nextafter(t_hit, np.float32(np.inf)),
                      np.float32(0.5) * t_hit, (rng.random(len(t_hit)) * 2 * t_hit).astype(np.float32)):
            (t_ref2, p_ref2), (t_dir2, p_dir2) = _cast_both(ref, bvh, oh, d[hit], limit.astype(np.float32))
            assert _same_bits(t_dir2, t_ref2) and np.array_equal(p_dir2, p_ref2), (name, what)
    assert hits > 1000 and misses > 1000


@same_isa_as_embreex
def test_direct_cast_equals_embreex_on_a_lidar_frame(meshes):
    """The HDL-64E rays of the scene's first ego pose on the background, one (1, 3) origin; and
    every partial packet size on a prefix of them."""
    from adv3d_runner.sensors.lidar import MountedLidar

    v, f, ref, bvh = meshes["background"]
    sensor = MountedLidar("hdl64", (0, 0, 1.73, 0, 0, 0))
    d = np.ascontiguousarray(sensor.dirs, np.float32)
    o = np.array([[3.0, -1.5, 1.73]], np.float32)
    (t_ref, p_ref), (t_dir, p_dir) = _cast_both(ref, bvh, o, d, np.full(len(d), 120.0, np.float32))
    assert (p_ref >= 0).sum() > 50_000 and (p_ref < 0).sum() > 10_000
    assert _same_bits(t_dir, t_ref) and np.array_equal(p_dir, p_ref)
    # Every packet size (N mod 8 and 16 from 0 to 15), from a row that hits the road.
    start = int(np.flatnonzero(p_ref >= 0)[0])
    for n in list(range(1, 34)) + [1000, 1001]:
        dn = d[start:start + n]
        (t1, p1), (t2, p2) = _cast_both(ref, bvh, o, dn, np.full(n, 120.0, np.float32))
        assert _same_bits(t2, t1) and np.array_equal(p2, p1) and np.array_equal(p2, p_ref[start:start + n]), n
    # (N, 3) origins repeating the one origin: the same as the broadcast.
    t_rows = np.full(len(d), 120.0, np.float32)
    p_rows, _ = bvh.intersect(np.repeat(o, len(d), axis=0), d, t_rows)
    assert _same_bits(t_rows, t_dir) and np.array_equal(p_rows, p_dir)


@same_isa_as_embreex
def test_the_identity_check_sees_one_ulp(meshes):
    """The comparison above can fail: a scene without RTC_SCENE_FLAG_ROBUST gives distances that
    differ from embreex's (robust) ones by an ulp on part of the same rays."""
    from adv3d_runner.sensors import embree

    v, f, ref, bvh = meshes["background"]
    loose = embree.TriangleScene(v, f, robust=False)
    o, d, tfar = _ray_sets(v, f, np.random.default_rng(7))["random"]
    t_ref = tfar.copy()
    _embreex_cast(ref, o, d, t_ref)
    t_loose = tfar.copy()
    loose.intersect(o, d, t_loose)
    assert not _same_bits(t_loose, t_ref)
    assert np.allclose(t_loose, t_ref, rtol=4 * EPS32)


def test_strided_tfar_is_written_in_place():
    box = trimesh.creation.box((1, 1, 1))
    bvh = MeshBVH(box.vertices + [10, 0, 0], box.faces)
    d = np.array([[1, 0, 0], [0, 1, 0], [1, 0.01, 0]], np.float32)
    t = np.full(6, 100, np.float32)
    prim, _ = bvh.intersect(np.zeros((1, 3), np.float32), d, t[::2])
    assert (prim[[0, 2]] >= 0).all() and prim[1] == -1
    assert abs(t[0] - 9.5) < 1e-5 and t[2] == 100 and t[4] < 10 and (t[1::2] == 100).all()
    with pytest.raises(ValueError):
        bvh.intersect(np.zeros((1, 3), np.float32), d, np.full(3, 100, np.float64))


def test_direct_binding_found():
    """On Linux x86-64 (embreex's manylinux wheel) the binding must load: a silent fallback
    would keep the results but lose the speed."""
    import platform
    import sys

    from adv3d_runner.sensors import embree

    if not (sys.platform == "linux" and platform.machine() == "x86_64"):
        pytest.skip("embreex wheel layout checked on Linux x86-64 only")
    assert embree.available(), embree.unavailable_reason()
    assert embree.unavailable_reason() is None
    assert embree.library_path().name.startswith("libembree4") and embree.library_path().parent.name == "embreex.libs"


@same_isa_as_embreex
def test_fallback_to_embreex_when_unavailable(meshes, monkeypatch):
    """Without the library MeshBVH casts with embreex's run: same bits, and the same API."""
    from adv3d_runner.sensors import embree

    v, f, ref, direct = meshes["sedan"]
    monkeypatch.setattr(embree, "_STATE", {"lib": None, "reason": "test: no library"})
    assert not embree.available() and embree.unavailable_reason() == "test: no library"
    assert embree.library_path() is None
    with pytest.raises(RuntimeError, match="test: no library"):
        embree.TriangleScene(v, f)
    bvh = MeshBVH(v, f)
    assert not bvh.direct and direct.direct
    for what, (o, d, tfar) in _ray_sets(v, f, np.random.default_rng(11)).items():
        t1, t2 = tfar.copy(), tfar.copy()
        p1, n1 = bvh.intersect(o, d, t1)
        p2, _ = direct.intersect(o, d, t2)
        assert n1 is None and p1.dtype == np.int32
        assert _same_bits(t1, t2) and np.array_equal(p1, p2), what
    # the explicit choice, the empty mesh
    assert not MeshBVH(v, f, direct=False).direct
    assert not MeshBVH(np.zeros((0, 3)), np.zeros((0, 3), int)).direct
