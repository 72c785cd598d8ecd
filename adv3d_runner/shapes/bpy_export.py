"""Child-process helper: flatten an .fbx or .blend into a plain triangle PLY with bpy.

Run as ``python -m adv3d_runner.shapes.bpy_export INPUT OUTPUT.ply``. The runner never imports
bpy in its own process (bpy is large, slow to import and owns global state);
:func:`adv3d_runner.shapes.mesh_io.read_mesh` runs this module in a subprocess instead.

What is written: every mesh object instance of the scene (modifiers applied, world transform
applied, so unit scales such as FBX centimetres become Blender metres), triangulated, with one
RGBA colour per face taken from its material's base colour. Blender world frame: Z up. Cameras,
lights, empties and armatures are skipped. Exit status 0 on success, 2 with a message on
stderr when the file cannot be read or holds no mesh.
"""
from __future__ import annotations

import sys
from pathlib import Path


def _material_rgba(material) -> tuple[int, int, int, int]:
    """Base colour of a material as 8-bit RGBA (Principled BSDF input, else viewport colour)."""
    rgba = (0.8, 0.8, 0.8, 1.0)
    if material is not None:
        rgba = tuple(material.diffuse_color)
        shader = _surface_shader(material)
        if shader is not None:
            for name in ("Base Color", "Color"):
                socket = shader.inputs.get(name)
                if socket is not None and hasattr(socket, "default_value") and len(socket.default_value) == 4:
                    rgba = tuple(socket.default_value)
                    break
    # linear -> sRGB so the glTF baseColorFactor round-trips to the same look
    def to_srgb(c: float) -> float:
        c = min(max(c, 0.0), 1.0)
        return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055

    return tuple(int(round(255 * v)) for v in (to_srgb(rgba[0]), to_srgb(rgba[1]), to_srgb(rgba[2]), min(max(rgba[3], 0), 1)))


def _surface_shader(material):
    """The shader node feeding the active material output (None without a node tree)."""
    tree = material.node_tree
    if tree is None:
        return None
    output = tree.get_output_node("ALL") or tree.get_output_node("EEVEE") or tree.get_output_node("CYCLES")
    if output is None or not output.inputs["Surface"].links:
        return None
    return output.inputs["Surface"].links[0].from_node


def load_into_blender(path: Path) -> None:
    """Open a .blend, or import an .fbx into an empty scene."""
    import bpy

    suffix = path.suffix.lower()
    if suffix == ".blend":
        bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    elif suffix == ".fbx":
        bpy.ops.wm.read_factory_settings(use_empty=True)
        result = bpy.ops.import_scene.fbx(filepath=str(path))
        if "FINISHED" not in result:
            raise RuntimeError(f"FBX import did not finish ({result})")
    else:
        raise RuntimeError(f"unsupported extension {suffix!r} (expected .fbx or .blend)")


def collect_triangles(depsgraph):
    """World-space triangles of every visible mesh instance.

    Returns:
        vertices (n, 3) float64 list, faces (m, 3) int list, colours (m, 4) uint8 list.
    """
    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    colours: list[tuple[int, int, int, int]] = []
    for inst in depsgraph.object_instances:
        obj = inst.object
        if obj.type != "MESH" or obj.original.hide_render:
            continue
        matrix = inst.matrix_world.copy()
        mesh = obj.to_mesh()
        try:
            mesh.calc_loop_triangles()
            offset = len(vertices)
            vertices.extend(tuple(matrix @ v.co) for v in mesh.vertices)
            palette = [_material_rgba(slot.material) for slot in obj.material_slots] or [_material_rgba(None)]
            # a negative-determinant transform mirrors the mesh: flip winding to keep normals out
            flip = matrix.to_3x3().determinant() < 0
            for tri in mesh.loop_triangles:
                a, b, c = (offset + i for i in tri.vertices)
                faces.append((a, c, b) if flip else (a, b, c))
                colours.append(palette[min(tri.material_index, len(palette) - 1)])
        finally:
            obj.to_mesh_clear()
    return vertices, faces, colours


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: python -m adv3d_runner.shapes.bpy_export INPUT(.fbx|.blend) OUTPUT.ply", file=sys.stderr)
        return 2
    src, dst = Path(argv[0]), Path(argv[1])
    try:
        import bpy
    except ImportError as exc:
        print(f"the bpy module is not installed ({exc}); pip install bpy==5.0.1", file=sys.stderr)
        return 3
    try:
        load_into_blender(src)
        vertices, faces, colours = collect_triangles(bpy.context.evaluated_depsgraph_get())
    except Exception as exc:  # noqa: BLE001 - any Blender failure becomes one clear message
        print(f"Blender could not read {src}: {exc}", file=sys.stderr)
        return 2
    if not faces:
        print(f"{src} holds no mesh object with faces", file=sys.stderr)
        return 2

    import numpy as np
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                           face_colors=np.asarray(colours, dtype=np.uint8), process=False)
    dst.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=False))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
