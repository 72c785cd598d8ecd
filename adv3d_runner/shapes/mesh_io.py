"""Reading vehicle meshes from artist files and bringing them into the project convention.

Convention (docs/architecture.md, "Conventions"): metres, right-handed, +x front, +y left, +z up, origin at the centre of
the footprint (the x/y bounding box) on the ground (z = 0 is the lowest point, the tyres).

- glb / gltf / obj / ply / stl are read with trimesh; scenes are flattened with their node
  transforms.
- ApolloCar3D car-model JSON (``{"car_type", "vertices", "faces"}``, faces numbered from 1,
  metres, camera frame: x right, y down, z forward) is read here: up -y, front +z.
- ShapeNet OBJ (``model_normalized.obj`` of ShapeNetCore v2: +y up, front -z, normalised to a
  unit diagonal, so real dimensions are required) is an OBJ with its own axis defaults
  (:data:`CONVENTIONS`).
- AC3D ``.ac`` and TORCS ``.acc`` (y up; TORCS cars at true scale, x along the length) are
  read by :mod:`.ac3d`, one colour per face from the materials.
- fbx / blend are read by Blender in a child process (``adv3d_runner.shapes.bpy_export``) so
  this process never imports bpy; the child writes a plain PLY in Blender's Z-up world frame
  (metres, object scales such as FBX centimetres applied).

Library meshes are stored as glTF binaries in the glTF frame (Y up, +Z towards the viewer):
glTF (x, y, z) = convention (x, z, -y), so Blender's glTF importer shows them the right way up
with the car's front along Blender +X. :func:`read_library_mesh` undoes that.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, MeshImportError
from . import fma

TRIMESH_FORMATS = (".glb", ".gltf", ".obj", ".ply", ".stl")
BLENDER_FORMATS = (".fbx", ".blend")
JSON_FORMATS = (".json",)  # ApolloCar3D car models
AC3D_FORMATS = (".ac", ".acc")  # AC3D and TORCS's AC3D (shapes/ac3d.py)
SUPPORTED_FORMATS = TRIMESH_FORMATS + BLENDER_FORMATS + JSON_FORMATS + AC3D_FORMATS

#: Up axis each format declares (None: the format does not say; we assume +z, CAD style).
NATIVE_UP = {".glb": "+y", ".gltf": "+y", ".fbx": "+z", ".blend": "+z",
             ".obj": None, ".ply": None, ".stl": None, ".json": "-y", ".ac": "+y", ".acc": "+y"}

#: Axis conventions of the datasets people hold, beyond what a file format declares:
#: ``up``/``forward`` defaults (explicit --up/--forward win), whether the files are normalised
#: (real dimensions needed) and where the convention is documented.
CONVENTIONS = {
    # ApolloCar3D (Song et al., CVPR 2019) car models, e.g. the car_models_json of the PKU /
    # Baidu Kaggle release: camera frame, x right, y down, z forward; metres; faces from 1
    # (ApolloScapeAuto/dataset-api car_instance; the Kaggle kernels read them as
    # ``faces - 1`` and flip y to draw them upright).
    "apollocar3d": {"up": "-y", "forward": "+z", "normalised": False},
    # ShapeNetCore v2 ``model_normalized.obj``: +y up, front towards -z, centred and scaled to
    # a unit bounding-box diagonal (shapenet.org; the v2 OBJs were converted with Assimp,
    # which fixed v1's left-right flips). Real dimensions must be given.
    "shapenet": {"up": "+y", "forward": "-z", "normalised": True},
}

#: Rotation taking convention coordinates (z up) to glTF coordinates (y up): g = C2G @ c.
CONVENTION_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
GLTF_TO_CONVENTION = CONVENTION_TO_GLTF.T

UNIT_SCALES = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
DEFAULT_RGBA = (180, 180, 180, 255)
BPY_TIMEOUT_S = 300
#: Largest mesh file read (bytes): the library's meshes are < 1 MB, source packs' files a few MB.
MAX_MESH_BYTES = 512 * 2**20


# ----------------------------------------------------------------------------- reading

def read_mesh(path: str | Path) -> tuple[Any, dict]:
    """Read any supported file as one triangle mesh in its own file frame.

    Args:
        path: mesh file (.glb .gltf .obj .ply .stl through trimesh; .fbx .blend through bpy;
            ApolloCar3D .json and AC3D .ac / .acc read here).

    Returns:
        (mesh, info): a ``trimesh.Trimesh`` (float64 vertices, face colours RGBA uint8) and
        ``{"format": ".glb", "native_up": "+y" | "+z" | None, "reader": "trimesh" | "bpy"}``.

    Raises:
        MeshImportError: the file is missing, unreadable, not a mesh, or has no triangles;
            the message names the file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_FORMATS:
        raise MeshImportError(f"{path}: unsupported mesh format {suffix or '(none)'!r}; "
                              f"expected one of {' '.join(SUPPORTED_FORMATS)}")
    if not path.exists():
        raise MeshImportError(f"{path}: no such file")
    check_mesh_file(path)
    if suffix in BLENDER_FORMATS:
        mesh = _read_with_blender(path)
        reader = "bpy"
    elif suffix in JSON_FORMATS:
        mesh = read_apollocar3d_json(path)
        reader = "apollocar3d-json"
    elif suffix in AC3D_FORMATS:
        from .ac3d import read_ac3d

        mesh = read_ac3d(path)
        reader = "ac3d"
    else:
        mesh = _read_with_trimesh(path, suffix)
        reader = "trimesh"
    if len(mesh.faces) == 0:
        raise MeshImportError(f"{path}: the file holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshImportError(f"{path}: vertex coordinates are not all finite (NaN or inf)")
    return mesh, {"format": suffix, "native_up": NATIVE_UP[suffix], "reader": reader}


def detect_convention(path: str | Path) -> str | None:
    """The dataset convention a file follows by its name (``CONVENTIONS``), or None.

    ``.json`` car models are ApolloCar3D's; ``model_normalized.obj`` is ShapeNetCore v2's file
    name. Anything else follows its format's own axes.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        return "apollocar3d"
    if path.name.lower() == "model_normalized.obj":
        return "shapenet"
    return None


def read_apollocar3d_json(path: str | Path):
    """An ApolloCar3D car-model JSON as a mesh in its own (camera) frame.

    Contract: ``{"car_type": str, "vertices": [[x, y, z], ...], "faces": [[i, j, k], ...]}``
    with faces numbered from 1 (as the Kaggle / ApolloScape car_models_json files are).

    Returns:
        ``trimesh.Trimesh`` (float64 vertices, 0-based faces); ``metadata["car_type"]`` holds
        the car type.
    Raises:
        FileFormatError: not JSON, or a field breaks the contract (names the JSON path).
    """
    import trimesh

    from ..validate import Node

    node = Node.load(Path(path))
    node.object("an ApolloCar3D car model object {car_type, vertices, faces}")
    car_type = node["car_type"].string(empty=True) if "car_type" in node else ""
    vertices = node["vertices"].array((None, 3))
    if len(vertices) < 3:
        node["vertices"].fail("at least 3 vertices [x, y, z]", len(vertices))
    faces_node = node["faces"]
    faces = faces_node.array((None, 3))
    if len(faces) == 0:
        faces_node.fail("at least one face [i, j, k]", 0)
    bad = np.flatnonzero(np.any((faces != np.round(faces)) | (faces < 1) | (faces > len(vertices)), axis=1))
    if len(bad):
        faces_node.fail(f"vertex numbers from 1 to {len(vertices)} (faces are numbered from 1)",
                        faces[bad[0]].tolist(), at=f"[{int(bad[0])}]")
    mesh = trimesh.Trimesh(vertices, faces.astype(np.int64) - 1, process=False)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=np.tile(np.array(DEFAULT_RGBA, np.uint8),
                                                                        (len(mesh.faces), 1)))
    mesh.metadata["car_type"] = car_type
    return mesh
def check_mesh_file(path: str | Path) -> None:
    """``path`` is a regular file (not a folder, FIFO or device) of at most
    :data:`MAX_MESH_BYTES`; else ``MeshImportError`` naming it."""
    from ..errors import FileFormatError
    from ..fileio import check_regular_file

    try:
        st = check_regular_file(path, "mesh file")
    except FileFormatError as exc:
        raise MeshImportError(f"{path}: expected {exc.expected} (got {exc.got})") from None
    if st.st_size > MAX_MESH_BYTES:
        raise MeshImportError(f"{path}: expected a mesh file of at most {MAX_MESH_BYTES // 2**20} MiB "
                              f"(got {st.st_size // 2**20} MiB)")


def _read_with_trimesh(path: Path, suffix: str):
    import trimesh

    check_mesh_file(path)
    try:
        loaded = trimesh.load(str(path), file_type=suffix[1:], force="scene", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types for bad files
        raise MeshImportError(f"{path}: cannot read as {suffix[1:]} ({type(exc).__name__}: {exc})") from None
    mesh = flatten_scene(loaded)
    if mesh is None:
        raise MeshImportError(f"{path}: not a triangle mesh (no geometry with faces in the file)")
    return mesh


def flatten_scene(scene) -> Any:
    """Concatenate every mesh instance of a ``trimesh.Scene`` with its node transform applied.

    Each part keeps one colour per face (textures are sampled to colours), so material colours
    survive concatenation. Returns None when the scene has no faces.
    """
    import trimesh

    parts = []
    for node in scene.graph.nodes_geometry:  # graph order is the file's order: deterministic
        geom_name = scene.graph[node][1]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        colours = _face_colours(geom)
        vertices = np.asarray(geom.vertices, dtype=np.float64).copy()
        transform = _world_transform(scene.graph, node)
        part = trimesh.Trimesh(vertices.copy(), np.asarray(geom.faces, dtype=np.int64).copy(), process=False)
        part.apply_transform(transform)  # flips winding if mirrored
        # the positions again, rounded the same on every CPU (shapes/fma.py: BLAS kernels differ)
        part.vertices = fma.transform_points(vertices, transform)
        part.visual = trimesh.visual.ColorVisuals(part, face_colors=colours)
        parts.append(part)
    if not parts:
        return None
    return concatenate(parts)


def _world_transform(graph, node) -> np.ndarray:
    """``graph[node]``'s matrix (base frame to ``node``) as trimesh's ``SceneGraph.get`` builds
    it (the path's edge matrices, those within 1e-8 of the identity left out, multiplied as
    ``np.linalg.multi_dot`` does, then ``fix_rigid`` when the graph repairs rigid transforms),
    but multiplied by :func:`fma.chain`, so the result does not depend on the CPU's BLAS kernel.
    A path with an edge walked backwards (not in glTF files) keeps trimesh's own matrix."""
    from trimesh import transformations

    data = graph.transforms.edge_data
    start = graph.base_frame
    if node == start:
        matrix = np.eye(4)
    elif (start, node) in data:
        matrix = np.asarray(data[(start, node)]["matrix"], dtype=np.float64)
    else:
        path = graph.transforms.shortest_path(start, node)
        matrices = []
        for u, v in zip(path[:-1], path[1:]):
            forward = data.get((u, v))
            if forward is None:
                return np.array(graph[node][0], dtype=np.float64)
            if "matrix" in forward:
                matrices.append(np.asarray(forward["matrix"], dtype=np.float64))
        matrices = [m for m in matrices if np.abs(m - np.eye(4)).max() > 1e-8]
        matrix = fma.chain(matrices) if matrices else np.eye(4)
    if getattr(graph, "repair_rigid", None) is not None:
        matrix = transformations.fix_rigid(matrix, max_deviance=graph.repair_rigid)
    return np.array(matrix, dtype=np.float64)


def concatenate(parts: list) -> Any:
    """Concatenate meshes keeping face colours (plain arrays, no visual merging surprises)."""
    import trimesh

    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    vertices = np.vstack([p.vertices for p in parts])
    faces = np.vstack([p.faces + o for p, o in zip(parts, offsets)])
    colours = np.vstack([_face_colours(p) for p in parts])
    return trimesh.Trimesh(vertices, faces, face_colors=colours, process=False)


def _face_colours(mesh) -> np.ndarray:
    """One RGBA uint8 colour per face, whatever the visual kind (texture, vertex, face, none)."""
    n = len(mesh.faces)
    visual = mesh.visual
    try:
        kind = visual.kind
        if kind == "face":
            return np.asarray(visual.face_colors, dtype=np.uint8)[:, :4].copy()
        if kind == "texture":
            visual = visual.to_color()
            kind = visual.kind
        if kind == "vertex":
            vc = np.asarray(visual.vertex_colors, dtype=np.uint8)
            if vc.ndim == 1:  # one colour for the whole mesh (material without texture)
                return np.tile(vc[:4], (n, 1))
            return vc[mesh.faces[:, 0]][:, :4].copy()
        if kind == "face":
            return np.asarray(visual.face_colors, dtype=np.uint8)[:, :4].copy()
    except Exception:  # noqa: BLE001 - colour is cosmetic: never fail an import over it
        pass
    return np.tile(np.array(DEFAULT_RGBA, dtype=np.uint8), (n, 1))


def _read_with_blender(path: Path):
    """Run ``bpy_export`` in a child Python and read the PLY it writes."""
    import trimesh

    with tempfile.TemporaryDirectory(prefix="adv3d-bpy-") as tmp:
        out = Path(tmp) / "mesh.ply"
        cmd = [sys.executable, "-m", "adv3d_runner.shapes.bpy_export", str(path.resolve()), str(out)]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=BPY_TIMEOUT_S,
                                  cwd=str(Path(__file__).resolve().parents[2]))
        except subprocess.TimeoutExpired:
            raise MeshImportError(f"{path}: Blender did not finish reading it within {BPY_TIMEOUT_S} s") from None
        if proc.returncode != 0 or not out.is_file():
            tail = (proc.stderr or proc.stdout or "").strip().splitlines()[-3:]
            raise MeshImportError(f"{path}: Blender could not convert it (exit {proc.returncode}): "
                                  + " | ".join(tail))
        try:
            mesh = trimesh.load(str(out), file_type="ply", process=False)
        except Exception as exc:  # noqa: BLE001
            raise MeshImportError(f"{path}: Blender's export could not be read back ({exc})") from None
    mesh.visual = trimesh.visual.ColorVisuals(mesh, face_colors=_face_colours(mesh))
    return mesh


# ----------------------------------------------------------------------------- axes and units

_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


def parse_axis(text: str) -> np.ndarray:
    """``"+y"``, ``"-z"`` or ``"x"`` -> signed unit vector (3,)."""
    t = str(text).strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    name = t.lstrip("+-")
    if name not in _AXES or len(t) - len(name) > 1:
        raise ConfigError(f"axis must be one of +x -x +y -y +z -z (got {text!r})")
    return sign * _AXES[name]


def axis_name(vec: np.ndarray) -> str:
    i = int(np.argmax(np.abs(vec)))
    return ("+" if vec[i] > 0 else "-") + "xyz"[i]


def axes_rotation(up: str, forward: str) -> np.ndarray:
    """Rotation (3, 3) taking file coordinates to the convention, ``c = R @ v``.

    Rows are the file's forward, left (= up x forward, right-handed) and up axes, so R is a
    proper rotation (det +1) and never mirrors the mesh.
    """
    u, f = parse_axis(up), parse_axis(forward)
    if abs(float(u @ f)) > 0.5:
        raise ConfigError(f"up ({up}) and forward ({forward}) must be different axes")
    left = np.cross(u, f)
    return np.vstack([f, left, u])


def guess_forward(vertices: np.ndarray, up: str) -> str:
    """The longest horizontal extent is the vehicle's length axis; the sign is assumed '+'.

    Front and back cannot be told apart from geometry reliably, so callers must check the
    result on a rendered picture and pass ``forward`` explicitly where it is wrong.
    """
    u = parse_axis(up)
    extent = np.ptp(vertices, axis=0)
    extent[int(np.argmax(np.abs(u)))] = -1.0
    return "+" + "xyz"[int(np.argmax(extent))]


def guess_unit(length: float) -> str:
    """Unit of a vehicle file from its length: real road vehicles are 1.5 m .. 25 m long."""
    if length <= 60.0:
        return "m"
    if length <= 6000.0:
        return "cm"
    return "mm"


def to_convention(mesh, up: str | None = None, forward: str | None = None, unit: str = "auto",
                  native_up: str | None = None) -> tuple[Any, dict]:
    """Rotate, scale and move a mesh into the convention frame.

    Args:
        mesh: ``trimesh.Trimesh`` in its file frame (not modified).
        up, forward: file axes (``"+y"``...) that are up and the vehicle's front; None: ``up``
            from the format (``native_up``, else +z) and ``forward`` from :func:`guess_forward`.
        unit: ``m``, ``cm``, ``mm``, ``in`` or ``auto`` (from the length, :func:`guess_unit`).
        native_up: the up axis the file format declares, if any.

    Returns:
        (converted mesh, record) where the record says which axes and unit were used and why.
        Large coordinate offsets are removed in float64 before anything else, so a model at
        1e5 cm from its origin keeps full precision.
    """
    record: dict = {}
    if up is None:
        up = native_up or "+z"
        record["up"] = f"{axis_name(parse_axis(up))} ({'declared by the format' if native_up else 'assumed'})"
    else:
        record["up"] = f"{axis_name(parse_axis(up))} (given)"
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if forward is None:
        forward = guess_forward(vertices, up)
        record["forward"] = f"{forward} (guessed: longest horizontal axis; sign unchecked)"
    else:
        record["forward"] = f"{axis_name(parse_axis(forward))} (given)"
    rot = axes_rotation(up, forward)
    # centre first: large offsets would otherwise cost precision in every later step
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    local = (vertices - centre) @ rot.T
    length = float(np.ptp(local[:, 0])) if len(local) else 0.0
    if unit == "auto":
        unit = guess_unit(length)
        record["unit"] = f"{unit} (guessed from a file length of {length:.6g})"
    elif unit in UNIT_SCALES:
        record["unit"] = f"{unit} (given)"
    else:
        raise ConfigError(f"unit must be one of auto {' '.join(UNIT_SCALES)} (got {unit!r})")
    local = local * UNIT_SCALES[unit]
    local = _ground_and_centre(local)
    record["file_offset_removed"] = [float(v) + 0.0 for v in np.round(centre, 6)]  # + 0.0: no "-0.0"
    out = mesh.copy()
    out.vertices = local
    return out, record


def _ground_and_centre(v: np.ndarray) -> np.ndarray:
    """Move the x/y bounding-box centre to the origin and the lowest point to z = 0."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    shift = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    return v - shift


def scale_to_dimensions(mesh, dimensions: tuple[float, float, float]) -> tuple[Any, dict]:
    """Scale a convention-frame mesh (anisotropically) so its box is ``length x width x height``.

    Returns:
        (scaled mesh, record with original size and per-axis factors).
    """
    dims = np.asarray(dimensions, dtype=np.float64)
    if dims.shape != (3,) or not np.all(np.isfinite(dims)) or np.any(dims <= 0):
        raise ConfigError(f"--dimensions needs three positive numbers L W H in metres (got {dimensions})")
    size = np.ptp(mesh.vertices, axis=0)
    if np.any(size <= 0):
        raise MeshImportError(f"cannot scale a flat mesh (size {size.tolist()}) to {dims.tolist()}")
    factors = dims / size
    out = mesh.copy()
    out.vertices = _ground_and_centre(np.asarray(mesh.vertices) * factors)
    return out, {"size_before_scaling": [round(float(s), 4) for s in size],
                 "scale_factors": [round(float(f), 4) for f in factors]}


def mesh_dimensions(mesh) -> tuple[float, float, float]:
    """(length, width, height) of a convention-frame mesh's bounding box, metres."""
    size = np.ptp(np.asarray(mesh.vertices, dtype=np.float64), axis=0)
    return float(size[0]), float(size[1]), float(size[2])


# ----------------------------------------------------------------------------- library files

def export_library_glb(mesh) -> bytes:
    """Bytes of a compact glb holding ``mesh`` (convention frame) in the glTF frame.

    Faces are grouped by colour into one primitive per colour with a plain PBR base colour,
    so Blender shows the original paint. Output bytes depend only on the mesh (deterministic).
    """
    import trimesh

    colours = _face_colours(mesh)
    keys = colours.astype(np.uint32) @ np.array([1 << 24, 1 << 16, 1 << 8, 1], dtype=np.uint32)
    order = np.argsort(keys, kind="stable")
    scene = trimesh.Scene()
    vertices_gltf = np.asarray(mesh.vertices, dtype=np.float64) @ CONVENTION_TO_GLTF.T
    for n, key in enumerate(np.unique(keys)):
        sel = order[keys[order] == key]
        faces = mesh.faces[sel]
        used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
        rgba = colours[sel[0]]
        material = trimesh.visual.material.PBRMaterial(
            name=f"paint-{n:02d}", baseColorFactor=[int(c) for c in rgba], metallicFactor=0.0, roughnessFactor=0.6)
        part = trimesh.Trimesh(vertices_gltf[used], inverse.reshape(-1, 3), process=False)
        part.visual = trimesh.visual.TextureVisuals(material=material)
        scene.add_geometry(part, geom_name=f"part-{n:02d}", node_name=f"part-{n:02d}")
    return scene.export(file_type="glb", include_normals=False)


def write_library_glb(mesh, path: str | Path) -> None:
    """Write :func:`export_library_glb` atomically."""
    from ..fileio import atomic_write_bytes

    atomic_write_bytes(path, export_library_glb(mesh))


def read_library_mesh(path: str | Path):
    """Read a library glb back into the convention frame.

    Colour groups are re-joined (coincident vertices merged), so the mesh has the topology it
    was cleaned with. Returns a ``trimesh.Trimesh`` with float64 vertices and face colours.
    """
    path = Path(path)
    if not path.exists():
        raise MeshImportError(f"{path}: library mesh file is missing")
    mesh = _read_with_trimesh(path, path.suffix.lower() or ".glb")
    if path.suffix.lower() in (".glb", ".gltf"):
        mesh.vertices = np.asarray(mesh.vertices, dtype=np.float64) @ GLTF_TO_CONVENTION.T
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return mesh


def import_vehicle(path: str | Path, up: str | None = None, forward: str | None = None,
                   unit: str = "auto", dimensions: tuple[float, float, float] | None = None,
                   clean: bool = True, convention: str = "auto",
                   length: float | None = None) -> tuple[Any, dict, dict]:
    """Read, convert, clean and (optionally) scale one vehicle file.

    Args:
        convention: ``"auto"`` (:func:`detect_convention`), ``"none"`` (the format's own axes)
            or a key of :data:`CONVENTIONS` (``apollocar3d``, ``shapenet``): the default up and
            forward axes; explicit ``up``/``forward`` win.
        length: real length in m to scale to uniformly (``convert_vehicle``), or None.

    Returns:
        (mesh in the convention frame, curation record, cleaning report).

    Raises:
        ConfigError: unknown convention; a normalised dataset (ShapeNet) without
            ``dimensions``. MeshImportError: unreadable file, or extents that look rotated
            (see :func:`check_orientation`).
    """
    if convention == "auto":
        convention = detect_convention(path) or "none"
    if convention != "none" and convention not in CONVENTIONS:
        raise ConfigError(f"unknown convention {convention!r}; choose auto, none, {', '.join(CONVENTIONS)}")
    mesh, info = read_mesh(path)
    native_up = info["native_up"]
    extra: dict = {}
    if convention != "none":
        conv = CONVENTIONS[convention]
        if conv["normalised"] and dimensions is None:
            raise ConfigError(f"{path}: {convention} models are normalised to a unit size; give the real "
                              "--dimensions L W H of the vehicle")
        if up is None:
            up, extra["up"] = conv["up"], f"{conv['up']} ({convention} convention)"
        if forward is None:
            forward, extra["forward"] = conv["forward"], f"{conv['forward']} ({convention} convention)"
        extra["convention"] = convention
    if mesh.metadata.get("car_type"):
        extra["car_type"] = str(mesh.metadata["car_type"])
    converted, curation, report = convert_vehicle(
        mesh, info["reader"], info["format"][1:], up=up, forward=forward, unit=unit, native_up=native_up,
        dimensions=dimensions, length=length, clean=clean, source=str(path))
    curation.update(extra)
    return converted, curation, report


def check_orientation(size: np.ndarray, rot: np.ndarray, record: dict, source: str = "the mesh") -> None:
    """Refuse a conversion whose extents look rotated: a road vehicle is longer than it is
    tall and than it is wide (a 12 m bus is 3.2 m tall, a 2.6 m tall van 5+ m long).

    Args:
        size: (3,) extents of the converted mesh (length x, width y, height z), any unit.
        rot: the (3, 3) rotation used (rows: file axes of forward, left, up).
        record: the axis record of :func:`to_convention` (names where up/forward came from).
    Raises:
        MeshImportError: naming the file axes that became length, width and height and what to give.
    """
    length, width, height = (float(x) for x in size)
    if length >= height and length >= width:
        return
    names = [axis_name(r) for r in rot]  # file axes of +x (front), +y (left), +z (up)
    file_ext = {axis_name(r).lstrip("+-"): float(e) for r, e in zip(rot, size)}
    longest = max(file_ext, key=file_ext.get)
    what = "taller" if height > length else "wider"
    raise MeshImportError(
        f"{source}: with up {record.get('up')} and forward {record.get('forward')} the vehicle would be {what} "
        f"than long: length {length:.3g} along file axis {names[0].lstrip('+-')}, width {width:.3g} along "
        f"{names[1].lstrip('+-')}, height {height:.3g} along {names[2].lstrip('+-')} (file units). A vehicle's "
        f"longest axis is its length; the file's longest is {longest}: give --up (the file axis towards the roof) "
        f"and --forward (towards the front), e.g. --forward +{longest}")


def convert_vehicle(mesh, reader: str, file_format: str, *, up: str | None = None, forward: str | None = None,
                    unit: str = "auto", native_up: str | None = None,
                    dimensions: tuple[float, float, float] | None = None, length: float | None = None,
                    clean: bool = True, source: str = "the mesh") -> tuple[Any, dict, dict]:
    """Convert a mesh as read from a file (by trimesh, or by Blender in the add-on) into the
    convention frame, clean it and (optionally) scale it: the one recipe behind every import.

    Args:
        mesh: ``trimesh.Trimesh`` in its file frame.
        reader, file_format: recorded in the curation record (``"trimesh"``, ``"glb"``).
        up, forward, unit, native_up: see :func:`to_convention`.
        dimensions: (L, W, H) m to scale to, anisotropically (records ``size_before_scaling``,
            ``scale_factors``).
        length: m to scale to uniformly, after cleaning (records ``scaled_to_length`` too).
        source: names the file in errors.

    Returns:
        (mesh in the convention frame, curation record, cleaning report).

    Raises:
        MeshImportError: the converted extents look rotated (:func:`check_orientation`).
    """
    from .cleaning import clean_mesh

    converted, record = to_convention(mesh, up=up, forward=forward, unit=unit, native_up=native_up)
    up_used = up or native_up or "+z"
    fwd_used = forward or guess_forward(np.asarray(mesh.vertices, dtype=np.float64), up_used)
    check_orientation(np.array(mesh_dimensions(converted)), axes_rotation(up_used, fwd_used), record, source)
    curation: dict = {"reader": reader, "file_format": file_format, **record,
                      "size_after_unit_conversion": [round(v, 4) for v in mesh_dimensions(converted)]}
    report: dict = {}
    if clean:
        converted, report = clean_mesh(converted)
    if dimensions is not None:
        converted, scaled = scale_to_dimensions(converted, dimensions)
        curation.update(scaled)
    if length is not None:
        size = np.array(mesh_dimensions(converted))
        converted, scaled = scale_to_dimensions(converted, tuple(size * (length / size[0])))
        curation.update(scaled)
        curation["scaled_to_length"] = float(length)
    return converted, curation, report


# ----------------------------------------------------------------------------- writing meshes

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl")


def write_mesh(mesh, path: str | Path, up: str | None = None) -> Path:
    """Write a convention-frame ``trimesh.Trimesh`` to ``path`` atomically, format by extension.

    glTF is y-up, so .glb/.gltf get the library's glTF frame and open upright in Blender; the
    other formats keep the convention frame (z up, +x forward) unless ``up="Y"``: then they get
    the same y-up frame (x stays front; what Blender's OBJ importer expects with its defaults,
    forward -Z, up Y). A .gltf's buffer is one file named after it (``car.gltf`` +
    ``car.bin``), so several .gltf files can share a folder.

    Raises:
        ConfigError: the extension is not one of ``MESH_SUFFIXES``, or ``up`` is not Y or Z
            (glTF is always y-up).
    """
    from ..fileio import atomic_path

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ConfigError(f"{path.name}: mesh files must end in one of {', '.join(MESH_SUFFIXES)}")
    gltf = suffix in (".glb", ".gltf")
    if up not in (None, "Y", "Z") or (gltf and up == "Z"):
        raise ConfigError(f"{path.name}: up axis must be Y or Z (glTF: Y), got {up!r}")
    out = mesh
    if gltf or up == "Y":
        out = mesh.copy()
        out.vertices = np.asarray(mesh.vertices) @ CONVENTION_TO_GLTF.T
    if suffix == ".gltf":
        _write_gltf(out, path)
        return path
    with atomic_path(path, suffix=suffix) as tmp:
        out.export(tmp, file_type=suffix.lstrip("."))
    return path


def _write_gltf(mesh, path: Path) -> None:
    """A .gltf whose single buffer is ``<stem>.bin`` beside it (trimesh's default names,
    ``gltf_buffer_N.bin``, would collide between files of one folder); buffer first, then the
    JSON, each atomically."""
    import json

    import trimesh
    from trimesh.exchange.gltf import export_gltf

    from ..fileio import atomic_write_bytes

    files = export_gltf(trimesh.Scene(mesh), merge_buffers=True)
    doc = json.loads(files.pop("model.gltf"))
    bin_name = f"{path.stem}.bin"
    for buf in doc.get("buffers", []):
        data = files.pop(buf["uri"])
        buf["uri"] = bin_name
        atomic_write_bytes(path.with_name(bin_name), data)
    atomic_write_bytes(path, json.dumps(doc, separators=(",", ":")).encode())
