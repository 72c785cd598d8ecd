"""Mesh import and conversion to the convention (metres, +x front, z up, origin on the ground)."""
from __future__ import annotations

import importlib.util
import itertools
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import trimesh

from adv3d_runner.errors import ConfigError, MeshImportError
from adv3d_runner.shapes import mesh_io


def car_like(length=4.5, width=1.8, height=1.5) -> trimesh.Trimesh:
    """A box body with a small 'nose' block in front (+x) and a 'mirror' on the left (+y)."""
    body = trimesh.creation.box(extents=(length, width, height))
    body.apply_translation((0, 0, height / 2))
    nose = trimesh.creation.box(extents=(0.2, 0.4, 0.2))
    nose.apply_translation((length / 2 + 0.1, 0, 0.5))
    mirror = trimesh.creation.box(extents=(0.1, 0.2, 0.1))
    mirror.apply_translation((0.5, width / 2 + 0.1, 1.0))
    return trimesh.util.concatenate([body, nose, mirror])


def _mirror_on_left(mesh) -> bool:
    """The vertices furthest left (+y) are the mirror's (z near 1 m), not the body's."""
    v = np.asarray(mesh.vertices)
    left = v[np.isclose(v[:, 1], v[:, 1].max(), atol=1e-6)]
    right = v[np.isclose(v[:, 1], v[:, 1].min(), atol=1e-6)]
    return bool(np.all(np.abs(left[:, 2] - 1.0) < 0.1) and np.ptp(right[:, 2]) > 1.0)


def _check_convention(mesh, dims, tol=1e-6):
    lo, hi = mesh.bounds
    assert hi - lo == pytest.approx(np.asarray(dims), abs=tol)
    assert lo[2] == pytest.approx(0.0, abs=tol)
    assert 0.5 * (lo[:2] + hi[:2]) == pytest.approx([0.0, 0.0], abs=tol)


def test_centimetres_and_large_offset_become_metres_on_the_ground(tmp_path):
    m = car_like()
    m.apply_scale(100.0)                          # centimetres
    m.apply_translation((1e5, -2e5, 3e5))         # far from the file's origin
    path = tmp_path / "car_cm.ply"
    m.export(path)                                # binary PLY keeps float64? not required
    out, cur, rep = mesh_io.import_vehicle(path, up="+z", forward="+x")
    assert cur["unit"].startswith("cm")
    _check_convention(out, (4.5 + 0.2, 1.8 + 0.2, 1.5), tol=1e-3)
    # the nose is in front (+x), the mirror on the left (+y)
    assert out.vertices[:, 0].max() == pytest.approx(out.bounds[1, 0])
    nose_x = out.vertices[np.argmax(out.vertices[:, 0]), 0]
    assert nose_x > 2.3
    assert _mirror_on_left(out)


def test_explicit_unit_overrides_guess(tmp_path):
    m = car_like()
    path = tmp_path / "car.obj"
    m.export(path)
    out, cur, _ = mesh_io.import_vehicle(path, up="+z", forward="+x", unit="mm")
    assert cur["unit"].startswith("mm")
    assert out.extents[0] == pytest.approx(4.7e-3, rel=1e-6)


def test_gltf_y_up_front_z_converts_with_left_kept(tmp_path):
    # a car authored in glTF's frame: up +y, front +z; left = up x front = +x
    m = car_like()
    to_gltf = np.eye(4)
    to_gltf[:3, :3] = np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0]])  # conv x->gltf z, y->x, z->y
    m.apply_transform(to_gltf)
    path = tmp_path / "car.glb"
    trimesh.Scene(m).export(path)
    out, cur, _ = mesh_io.import_vehicle(path, forward="+z")
    assert cur["up"].startswith("+y")  # declared by glTF
    _check_convention(out, (4.7, 2.0, 1.5), tol=1e-5)
    assert out.vertices[:, 0].max() > 2.3                  # nose front
    assert _mirror_on_left(out)  # not mirrored


def test_scene_nodes_are_flattened_with_transforms(tmp_path):
    a = trimesh.creation.box(extents=(1, 1, 1))
    scene = trimesh.Scene()
    t1, t2 = np.eye(4), np.eye(4)
    t1[:3, 3] = (0, 0, 0)
    t2[:3, 3] = (5, 0, 0)
    scene.add_geometry(a, node_name="a", geom_name="box", transform=t1)
    scene.add_geometry(a, node_name="b", geom_name="box", transform=t2)  # instanced geometry
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh, info = mesh_io.read_mesh(path)
    assert len(mesh.faces) == 24
    assert mesh.bounds[:, 0] == pytest.approx([-0.5, 5.5])


def test_guess_forward_is_longest_horizontal_axis():
    v = np.array([[0, 0, 0], [1.0, 5.0, 9.0]])  # z is longest but up
    assert mesh_io.guess_forward(v, "+z") == "+y"
    assert mesh_io.guess_forward(v, "+y") == "+z"


@pytest.mark.parametrize("up,forward", [(u, f) for u, f in itertools.product(
    ["+x", "-x", "+y", "-y", "+z", "-z"], repeat=2) if u[1] != f[1]])
def test_axes_rotation_is_proper_and_maps_axes(up, forward):
    r = mesh_io.axes_rotation(up, forward)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert r @ mesh_io.parse_axis(forward) == pytest.approx([1, 0, 0])
    assert r @ mesh_io.parse_axis(up) == pytest.approx([0, 0, 1])


def test_bad_axes_rejected():
    with pytest.raises(ConfigError):
        mesh_io.axes_rotation("+z", "-z")
    with pytest.raises(ConfigError):
        mesh_io.parse_axis("up")


def test_scale_to_dimensions_is_anisotropic_and_recorded():
    m, _ = mesh_io.to_convention(car_like(2.0, 1.5, 1.2), up="+z", forward="+x", unit="m")
    out, rec = mesh_io.scale_to_dimensions(m, (4.7, 1.8, 1.45))
    _check_convention(out, (4.7, 1.8, 1.45))
    assert rec["size_before_scaling"] == pytest.approx([2.2, 1.7, 1.2], abs=1e-4)
    assert rec["scale_factors"] == pytest.approx([4.7 / 2.2, 1.8 / 1.7, 1.45 / 1.2], abs=1e-4)


# ----------------------------------------------------------------------------- bad files

def test_text_file_named_glb_is_a_clear_error(tmp_path):
    path = tmp_path / "not_a_mesh.glb"
    path.write_text("hello, I am not a glTF binary\n")
    with pytest.raises(MeshImportError, match="not_a_mesh.glb"):
        mesh_io.read_mesh(path)


def test_truncated_glb_is_a_clear_error(tmp_path):
    good = tmp_path / "good.glb"
    trimesh.Scene(car_like()).export(good)
    data = good.read_bytes()
    bad = tmp_path / "truncated.glb"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshImportError, match="truncated.glb"):
        mesh_io.read_mesh(bad)


def test_missing_unsupported_and_empty_files(tmp_path):
    with pytest.raises(MeshImportError, match="nope.obj"):
        mesh_io.read_mesh(tmp_path / "nope.obj")
    odd = tmp_path / "car.xyz"
    odd.write_text("1 2 3\n")
    with pytest.raises(MeshImportError, match="unsupported"):
        mesh_io.read_mesh(odd)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(MeshImportError, match="empty.obj"):
        mesh_io.read_mesh(empty)
    points = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(points)
    with pytest.raises(MeshImportError, match="points.ply"):
        mesh_io.read_mesh(points)


def test_nan_vertices_rejected(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(MeshImportError, match="nan.obj"):
        mesh_io.read_mesh(path)


# ----------------------------------------------------------------------------- library glb

def test_library_glb_round_trip_is_exact_to_float32_and_deterministic(tmp_path):
    m, _ = mesh_io.to_convention(car_like(), up="+z", forward="+x", unit="m")
    colours = np.tile([50, 60, 70, 255], (len(m.faces), 1)).astype(np.uint8)
    colours[:12] = [255, 0, 0, 255]
    m.visual = trimesh.visual.ColorVisuals(m, face_colors=colours)
    data = mesh_io.export_library_glb(m)
    assert data == mesh_io.export_library_glb(m)
    path = tmp_path / "car.glb"
    path.write_bytes(data)
    back = mesh_io.read_library_mesh(path)
    assert len(back.faces) == len(m.faces)
    assert back.bounds == pytest.approx(m.bounds, abs=1e-6)
    # stored in the glTF frame (Y up): read raw, the height lies along the file's y axis
    raw, _ = mesh_io.read_mesh(path)
    assert raw.extents[1] == pytest.approx(1.5, abs=1e-6)
    red = np.all(np.asarray(back.visual.face_colors) == [255, 0, 0, 255], axis=1)
    assert red.sum() == 12


# ----------------------------------------------------------------------------- bpy path

_BPY = importlib.util.find_spec("bpy") is not None

_MAKE_FBX = textwrap.dedent("""
    import sys, bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=2.0, location=(0, 0, 0))
    car = bpy.context.active_object
    car.scale = (2.25, 0.9, 0.75)      # 4.5 x 1.8 x 1.5 m box
    car.location = (100.0, 200.0, 5.0)
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(102.35, 200.0, 5.0))  # nose at +x
    bpy.ops.object.camera_add(location=(0, -10, 2))   # non-mesh objects are skipped
    bpy.ops.object.empty_add(location=(0, 0, -50))     # (lights break the FBX importer of bpy 5.0.1)
    out = sys.argv[-1]
    if out.endswith(".fbx"):
        bpy.ops.export_scene.fbx(filepath=out, global_scale=1.0)
    else:
        bpy.ops.wm.save_as_mainfile(filepath=out)
""")


@pytest.mark.blender
@pytest.mark.skipif(not _BPY, reason="bpy not installed")
@pytest.mark.parametrize("ext", [".fbx", ".blend"])
def test_fbx_and_blend_import_through_bpy_subprocess(tmp_path, ext):
    src = tmp_path / f"box{ext}"
    subprocess.run([sys.executable, "-c", _MAKE_FBX, str(src)], check=True, capture_output=True, timeout=120)
    had_bpy = "bpy" in sys.modules  # other tests in this session may have imported it
    out, cur, rep = mesh_io.import_vehicle(src, forward="+x")
    assert had_bpy or "bpy" not in sys.modules  # the runner process itself never imports bpy
    assert cur["reader"] == "bpy" and cur["up"].startswith("+z")
    _check_convention(out, (4.7, 1.8, 1.5), tol=1e-4)  # body 4.5 + nose sticking out 0.2
    assert rep["components"] == 2
    front = out.vertices[np.isclose(out.vertices[:, 0], out.bounds[1, 0], atol=1e-5)]
    assert np.ptp(front[:, 2]) == pytest.approx(0.2, abs=1e-4)  # the nose is at +x


@pytest.mark.blender
@pytest.mark.skipif(not _BPY, reason="bpy not installed")
def test_corrupt_blend_names_the_file(tmp_path):
    bad = tmp_path / "broken.blend"
    bad.write_bytes(b"BLENDER-v300" + b"\x00garbage" * 10)
    with pytest.raises(MeshImportError, match="broken.blend"):
        mesh_io.read_mesh(bad)


def test_runner_modules_never_import_bpy():
    # a fresh interpreter: the blender tests of this session may have imported bpy already
    code = (
        "import sys, adv3d_runner.cli, adv3d_runner.shapes.mesh_io, adv3d_runner.shapes.library;"
        "adv3d_runner.cli.build_parser();"
        "sys.exit(1 if 'bpy' in sys.modules or 'torch' in sys.modules else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


# ----------------------------------------------------------------------------- datasets' conventions

def _apollo_json(path, mesh, car_type="3x"):
    """Write ``mesh`` (convention frame) as an ApolloCar3D car model: camera frame x right,
    y down, z forward; faces numbered from 1."""
    import json

    v = np.asarray(mesh.vertices)
    cam = np.c_[-v[:, 1], -v[:, 2], v[:, 0]]  # right = -left, down = -up, forward = +x
    path.write_text(json.dumps({"car_type": car_type, "vertices": cam.tolist(),
                                "faces": (np.asarray(mesh.faces) + 1).tolist()}))
    return path


def test_apollocar3d_json_is_read_upright_with_front_and_left_kept(tmp_path):
    path = _apollo_json(tmp_path / "dazhongmaiteng.json", car_like())
    out, cur, rep = mesh_io.import_vehicle(path)
    _check_convention(out, (4.5 + 0.2, 1.8 + 0.2, 1.5))
    assert out.vertices[np.argmax(out.vertices[:, 0]), 2] == pytest.approx(0.5 - 0.1, abs=0.11)  # the nose
    assert _mirror_on_left(out)
    assert cur["convention"] == "apollocar3d" and cur["car_type"] == "3x"
    assert cur["up"].startswith("-y") and cur["forward"].startswith("+z")
    assert cur["reader"] == "apollocar3d-json" and rep["triangles"] == len(car_like().faces)


def test_apollocar3d_json_faces_must_be_numbered_from_one(tmp_path):
    import json

    from adv3d_runner.errors import FileFormatError

    path = _apollo_json(tmp_path / "car.json", car_like())
    doc = json.loads(path.read_text())
    doc["faces"][5] = [0, 1, 2]  # 0 is not a vertex number
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match=r"car\.json.*\$\.faces\[5\].*numbered from 1"):
        mesh_io.import_vehicle(path)
    doc["faces"][5] = [1, 2]
    path.write_text(json.dumps(doc))
    with pytest.raises(FileFormatError, match=r"\$\.faces"):
        mesh_io.import_vehicle(path)


def test_shapenet_obj_convention_and_real_dimensions(tmp_path):
    """ShapeNetCore v2 ``model_normalized.obj``: +y up, front -z, unit diagonal."""
    m = car_like()
    v = np.asarray(m.vertices)
    sn = np.c_[-v[:, 1], v[:, 2], -v[:, 0]]  # x right (= -left), y up, z back (front at -z)
    sn = (sn - sn.mean(axis=0)) / np.linalg.norm(np.ptp(sn, axis=0))
    folder = tmp_path / "02958343" / "abc123" / "models"
    folder.mkdir(parents=True)
    path = folder / "model_normalized.obj"
    trimesh.Trimesh(sn, m.faces, process=False).export(path)
    with pytest.raises(ConfigError, match="dimensions"):
        mesh_io.import_vehicle(path)
    out, cur, _ = mesh_io.import_vehicle(path, dimensions=(4.7, 2.0, 1.5))
    _check_convention(out, (4.7, 2.0, 1.5), tol=1e-4)
    assert cur["convention"] == "shapenet" and cur["forward"].startswith("-z")
    assert out.vertices[np.argmax(out.vertices[:, 0]), 2] < 0.7  # the nose is in front
    assert _mirror_on_left(out)
    # the same file under another name follows the plain OBJ default (+z up) unless told
    other = tmp_path / "car.obj"
    trimesh.Trimesh(sn * 4.0, m.faces, process=False).export(other)
    with pytest.raises(MeshImportError, match="taller than long"):
        mesh_io.import_vehicle(other)
    out2, _, _ = mesh_io.import_vehicle(other, convention="shapenet", dimensions=(4.7, 2.0, 1.5))
    assert np.allclose(out2.bounds, out.bounds, atol=1e-4)


def test_rotated_extents_are_refused_naming_the_axes(tmp_path):
    """A Y-up car read with the assumed +z up would stand on its nose: refused, and the
    message names the file axes and what to pass."""
    m = car_like()
    v = np.asarray(m.vertices)
    path = tmp_path / "yup.ply"
    trimesh.Trimesh(np.c_[v[:, 1], v[:, 2], v[:, 0]], m.faces, process=False).export(path)  # x left, y up, z front
    with pytest.raises(MeshImportError) as exc:
        mesh_io.import_vehicle(path)
    msg = str(exc.value)
    assert "yup.ply" in msg and "taller than long" in msg and "height 4.7 along z" in msg
    assert "--up" in msg and "--forward +z" in msg
    out, _, _ = mesh_io.import_vehicle(path, up="+y", forward="+z")
    _check_convention(out, (4.5 + 0.2, 1.8 + 0.2, 1.5))


def test_up_minus_y_works_as_the_docs_write_it(tmp_path, capsys):
    """``--up -y`` (space, not ``=``) reaches the importer: argparse alone reads ``-y`` as an option."""
    from adv3d_runner.cli import main

    m = car_like()
    v = np.asarray(m.vertices)
    pack = tmp_path / "pack"
    pack.mkdir()
    (pack / "License.txt").write_text("Creative Commons Zero, CC0")
    path = pack / "down.ply"
    # file frame: x front, y down, z left (right-handed)
    trimesh.Trimesh(np.c_[v[:, 0], -v[:, 2], v[:, 1]], m.faces, process=False).export(path)
    lib = tmp_path / "lib" / "library.json"
    rc = main(["-q", "assets", "import", str(path), "--class", "sedan", "--up", "-y", "--forward", "+x",
               "--library", str(lib)])
    assert rc == 0, capsys.readouterr().err
    from adv3d_runner.shapes.library import load_asset_mesh, load_library

    library = load_library(lib)
    asset = library.assets[0]
    assert asset.curation["up"] == "-y (given)"
    out = load_asset_mesh(library, asset.id)
    _check_convention(out, (4.5 + 0.2, 1.8 + 0.2, 1.5), tol=1e-5)
    assert _mirror_on_left(out)


# ----------------------------------------------------------------------------- CPU-independent rounding

def test_fma_is_one_correctly_rounded_operation():
    from fractions import Fraction

    from adv3d_runner.shapes import fma

    rng = np.random.default_rng(7)
    n = 1500
    a = rng.standard_normal(n) * np.exp2(rng.integers(-30, 30, n))
    b = rng.standard_normal(n) * np.exp2(rng.integers(-30, 30, n))
    # near-cancellation (the hard cases), unrelated addends, exact halves and zeros
    for c in (-(a * b) * (1 + rng.integers(-3, 4, n) * 2.0 ** -52), rng.standard_normal(n), 0.5 * a * b,
              np.zeros(n)):
        got = fma.fma(a, b, c)
        want = np.array([float(Fraction(x) * Fraction(y) + Fraction(z)) for x, y, z in zip(a, b, c)])
        assert np.array_equal(got, want)
    # a product whose exact value is lost by rounding it first: 1 + 2^-30 squared, minus 1
    x = 1.0 + 2.0 ** -30
    assert fma.fma(x, x, -1.0) == 2.0 ** -29 + 2.0 ** -60
    assert (x * x) - 1.0 == 2.0 ** -29


def _cpu_has_avx2_and_fma() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            flags = set(f.read().split())
    except OSError:
        return False
    return {"avx2", "fma"} <= flags


_AVX2_FMA = _cpu_has_avx2_and_fma()


@pytest.mark.skipif(not _AVX2_FMA, reason="needs a Linux x86-64 CPU with AVX2 and FMA (OpenBLAS's FMA kernels)")
def test_fma_products_equal_openblas_fma_kernels_on_every_kernel_choice():
    """shapes/fma.py computes what OpenBLAS's FMA kernels compute, bit for bit, whichever kernel
    this process's OpenBLAS runs (the SSE Prescott kernel, which numpy 1.26's OpenBLAS picks on
    CPUs it does not know, rounds differently): the library rebuild no longer depends on it."""
    script = textwrap.dedent("""
        import sys
        import numpy as np
        import trimesh
        from adv3d_runner.shapes import fma
        rng = np.random.default_rng(3)
        same = blas_same = True
        for n in (2, 3, 4, 5):
            ms = [rng.standard_normal((4, 4)) for _ in range(n)]
            same &= np.array_equal(fma.chain(ms).view(np.int64), np.linalg.multi_dot(ms).view(np.int64))
        m = rng.standard_normal((4, 4))
        p = rng.standard_normal((2000, 3))
        same &= np.array_equal(fma.transform_points(p, m).view(np.int64),
                               trimesh.transformations.transform_points(p, m).view(np.int64))
        print(int(same), fma.transform_points(p, m).tobytes().hex()[:64] + fma.chain(ms).tobytes().hex())
    """)
    from adv3d_runner.machine import cpu_flags

    # Only the kernels this CPU can run: forcing one it cannot dies of SIGILL.
    needs = {"Prescott": {"pni"}, "Haswell": {"avx2", "fma"}, "Zen": {"avx2", "fma"},
             "SkylakeX": {"avx512f", "avx512cd", "avx512dq", "avx512bw", "avx512vl"}}
    runnable = [k for k, flags in needs.items() if flags <= cpu_flags()]  # pni: SSE3
    if "Haswell" not in runnable:
        pytest.skip(f"this CPU runs none of OpenBLAS's FMA kernels (runs {runnable})")
    out = {}
    for kernel in runnable:
        env = {**__import__("os").environ, "OPENBLAS_CORETYPE": kernel}
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
        assert res.returncode == 0, res.stderr
        out[kernel] = res.stdout.split()
    assert [out[k][0] for k in runnable if k != "Prescott"] == ["1"] * (len(runnable) - 1)  # equal to the FMA kernels
    assert out["Prescott"][0] == "0"  # the SSE kernel rounds differently (why fma.py exists)
    assert len({v[1] for v in out.values()}) == 1  # and fma.py's own results never change


def test_gltf_node_transforms_round_like_the_fma_kernels(tmp_path):
    """Nested rotated and scaled glTF nodes: the flattened vertices are the fma.py products of
    the nodes' matrices (the 2026-11-27 coupe.glb mismatch came from these)."""
    from adv3d_runner.shapes import fma

    rng = np.random.default_rng(11)
    scene = trimesh.Scene()
    box = trimesh.creation.box(extents=(1.3, 0.7, 0.4))
    box.vertices = box.vertices + rng.standard_normal(box.vertices.shape) * 0.01

    def trs(t, q, s):
        m = trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))
        m[:3, :3] *= s
        m[:3, 3] = t
        return m

    mats = [trs(rng.standard_normal(3), rng.standard_normal(4), rng.uniform(0.5, 2, 3)) for _ in range(3)]
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to="a", matrix=mats[0])
    scene.graph.update(frame_from="a", frame_to="b", matrix=mats[1])
    scene.add_geometry(box, geom_name="part", node_name="c", parent_node_name="b", transform=mats[2])
    path = tmp_path / "nested.glb"
    scene.export(path)

    loaded = trimesh.load(str(path), force="scene", process=False)
    ed = loaded.graph.transforms.edge_data
    chain = loaded.graph.transforms.shortest_path(loaded.graph.base_frame, "c")
    edges = [np.asarray(ed[(u, v)]["matrix"]) for u, v in zip(chain[:-1], chain[1:])]
    edges = [m for m in edges if np.abs(m - np.eye(4)).max() > 1e-8]
    assert len(edges) == 3
    geom = np.asarray(loaded.geometry["part"].vertices, dtype=np.float64)
    want = fma.transform_points(geom, fma.chain(edges))
    flat = mesh_io.flatten_scene(loaded)
    assert np.array_equal(flat.vertices, want)


def test_openmaterial_coupe_imports_to_the_shipped_bytes(repo_root):
    """The coupe is the library mesh that came out differently on a CPU whose OpenBLAS kernel
    does not fuse multiply-adds; importing it as build_library.sh does gives the shipped glb."""
    from adv3d_runner.shapes.library import DEFAULT_LIBRARY

    src = repo_root.parent / "shared" / "vehicle-packs" / "openmaterial-examples" / "vehicle_example.gltf"
    if not src.is_file():
        pytest.skip(f"source pack not found at {src}")
    mesh, _, _ = mesh_io.import_vehicle(src, up="+y", forward="-x")
    shipped = DEFAULT_LIBRARY.parent / "openmaterial-examples" / "coupe.glb"
    assert mesh_io.export_library_glb(mesh) == shipped.read_bytes()
