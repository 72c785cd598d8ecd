# SPDX-License-Identifier: GPL-3.0-or-later
"""Headless preview renders with bpy (Workbench or Eevee), run in a child process.

    python -m blender_addon.render --what library --out docs/images/library.png
    python -m blender_addon.render --what sweep --dim 0 --steps 5 --out sweep.png
    python -m blender_addon.render --what review --run runs/NAME --frame 20 --out review.png

``adv3d blender render`` starts this module so the runner process never imports bpy. Exit
status 2 with a one-line message on stderr for user errors (bad file, unknown dimension).

``--panel`` puts the panel's state beside the picture: the bpy module has no window to draw
Blender's UI in, so the column is drawn (Pillow) from the values of the panel's properties after
its operators ran: the library list, the slider values, the scene and attack settings, the
loaded replay. Each picture is thus a panel in use: what it shows and what it made.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

# Colours (linear RGB) for vehicles without paint and for the sweep's shapes.
BODY = (0.55, 0.58, 0.62, 1.0)
SWEEP = (0.85, 0.35, 0.15, 1.0)


def _reset(width: int, height: int, engine: str):
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.resolution_x = width
    scene.render.resolution_y = height
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"
    scene.render.image_settings.compression = 90
    if engine == "eevee":
        scene.render.engine = "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in _engines() else "BLENDER_EEVEE"
    else:
        scene.render.engine = "BLENDER_WORKBENCH"
        shading = scene.display.shading
        shading.light = "STUDIO"
        shading.color_type = "VERTEX"  # the active colour attribute
        shading.show_shadows = False
        shading.show_cavity = True
        shading.cavity_type = "WORLD"
        scene.display.shadow_focus = 0.2
    world = bpy.data.worlds.new("white")
    world.color = (0.92, 0.93, 0.95)
    scene.world = world
    scene.view_settings.view_transform = "Standard"
    return scene


def _engines() -> list[str]:
    import bpy

    return [item.identifier for item in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items]


def _mesh_object(name: str, vertices: np.ndarray, faces: np.ndarray, rgba, face_rgba=None):
    """Mesh object with a per-corner colour attribute (Workbench ATTRIBUTE colouring)."""
    import bpy

    from blender_addon import meshdata

    obj = meshdata.new_mesh_object(name, vertices, faces)
    mesh = obj.data
    attr = mesh.color_attributes.new("Col", "FLOAT_COLOR", "CORNER")
    if face_rgba is None:
        colours = np.tile(np.asarray(rgba, dtype=np.float32), (len(faces) * 3, 1))
    else:
        colours = np.repeat(np.asarray(face_rgba, dtype=np.float32), 3, axis=0)
    attr.data.foreach_set("color", colours.ravel())
    mesh.color_attributes.active_color = attr
    for poly in mesh.polygons:  # flat shading reads better for low-poly and marching-cubes meshes
        poly.use_smooth = False
    # A material carrying the same colour, for Eevee (Workbench reads the attribute).
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = rgba
    mesh.materials.append(mat)
    return obj


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _label(text: str, x: float, y: float, size: float = 0.45):
    import bpy

    curve = bpy.data.curves.new(text, "FONT")
    curve.body = text
    curve.size = size
    curve.align_x = "CENTER"
    obj = bpy.data.objects.new(text, curve)
    bpy.context.scene.collection.objects.link(obj)
    obj.location = (x, y, 0.0)
    mat = bpy.data.materials.new("label")
    mat.diffuse_color = (0.05, 0.05, 0.05, 1.0)
    curve.materials.append(mat)
    return obj


def _ground(bounds_lo: np.ndarray, bounds_hi: np.ndarray) -> None:
    margin = 3.0
    x0, y0 = bounds_lo[:2] - margin
    x1, y1 = bounds_hi[:2] + margin
    v = np.array([[x0, y0, -0.01], [x1, y0, -0.01], [x1, y1, -0.01], [x0, y1, -0.01]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    _mesh_object("ground", v, f, (0.80, 0.81, 0.83, 1.0))


def _camera_fit(lo: np.ndarray, hi: np.ndarray, elevation_deg: float = 35.0, azimuth_deg: float = -60.0,
                points: np.ndarray | None = None):
    """Orthographic camera looking down at the box [lo, hi] (or at ``points`` (N, 3)), fitted to it.

    ``azimuth_deg`` is where the camera stands seen from the target (-90: on the -y side,
    looking towards +y)."""
    import bpy
    from mathutils import Euler, Matrix, Vector

    scene = bpy.context.scene
    cam_data = bpy.data.cameras.new("camera")
    cam_data.type = "ORTHO"
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    rot = Euler((math.radians(90.0 - elevation_deg), 0.0, math.radians(azimuth_deg + 90.0)), "XYZ")
    if points is not None:
        lo, hi = points.min(axis=0), points.max(axis=0)
    centre = Vector(((lo + hi) / 2).tolist())
    rmat = rot.to_matrix()
    view_dir = rmat @ Vector((0.0, 0.0, -1.0))
    cam.rotation_euler = rot
    cam.location = centre - view_dir * 100.0
    # Fit: project the box corners onto the camera's x / y axes.
    corners = points if points is not None else np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    axes = np.array(rmat.transposed())[:2]  # camera x and y in world
    proj = (corners - np.array(centre)) @ axes.T
    w = np.ptp(proj[:, 0])
    h = np.ptp(proj[:, 1])
    aspect = scene.render.resolution_x / scene.render.resolution_y
    cam_data.ortho_scale = 1.08 * max(w, h * aspect)
    cam_data.clip_end = 1000.0
    _ = Matrix


PANEL_WIDTH = 330  # px, the sidebar column of --panel


def _render(out: Path, panel: tuple[str, list] | None = None) -> None:
    """Render the scene's camera to ``out``; ``panel`` = (title, lines) puts a sidebar column
    with the panel's state on the left (lines: text, or ("slider", label, value in [0, 1]))."""
    import bpy

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp.png")  # rename when complete: no half-written image
    bpy.context.scene.render.filepath = str(tmp)
    bpy.ops.render.render(write_still=True)
    try:  # an adaptive 256-colour palette: a third of the size, indistinguishable here
        from PIL import Image

        img = Image.open(tmp).convert("RGB")
        if panel is not None:
            img = _with_panel(img, *panel)
        img.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(tmp, optimize=True)
    except ImportError:
        if panel is not None:
            raise SystemExit(_fail("--panel needs Pillow"))
    tmp.replace(out)


def _with_panel(img, title: str, lines: list):
    """``img`` with a sidebar column on its left drawn in Blender's dark theme colours."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=13)
    bold = ImageFont.load_default(size=15)
    out = Image.new("RGB", (img.width + PANEL_WIDTH, img.height), (48, 48, 48))
    out.paste(img, (PANEL_WIDTH, 0))
    d = ImageDraw.Draw(out)
    d.rectangle([0, 0, PANEL_WIDTH - 1, 26], fill=(61, 61, 61))
    d.text((10, 5), title, font=bold, fill=(230, 230, 230))
    y = 34
    for line in lines:
        if y > img.height - 18:
            d.text((10, y), "...", font=font, fill=(200, 200, 200))
            break
        if isinstance(line, tuple) and line[0] == "slider":  # a Blender slider: filled in blue
            _, label, value = line
            d.rounded_rectangle([10, y, PANEL_WIDTH - 10, y + 18], 4, fill=(84, 84, 84))
            w = int((PANEL_WIDTH - 20) * min(max(value, 0.0), 1.0))
            if w > 4:
                d.rounded_rectangle([10, y, 10 + w, y + 18], 4, fill=(71, 114, 179))
            d.text((16, y + 2), label, font=font, fill=(235, 235, 235))
            d.text((PANEL_WIDTH - 56, y + 2), f"{value:.3f}", font=font, fill=(235, 235, 235))
            y += 22
        elif isinstance(line, tuple) and line[0] == "button":
            d.rounded_rectangle([10, y, PANEL_WIDTH - 10, y + 20], 4, fill=(84, 84, 84))
            d.text((PANEL_WIDTH // 2, y + 3), line[1], font=font, fill=(235, 235, 235), anchor="mt")
            y += 25
        elif isinstance(line, tuple) and line[0] == "head":
            y += 4
            d.text((10, y), line[1], font=bold, fill=(220, 220, 220))
            y += 21
        else:
            d.text((10, y), str(line)[:50], font=font, fill=(205, 205, 205))
            y += 18
    return out


# --------------------------------------------------------------------------- what to render

def render_library(library_path: Path | None, out: Path, width: int, height: int, engine: str,
                   panel: bool = False) -> None:
    """All library assets on a grid (rows by class order in the file), labelled with their ids."""
    from adv3d_runner.shapes.library import DEFAULT_LIBRARY, load_asset_mesh, load_library

    library = load_library(library_path or DEFAULT_LIBRARY)
    state = _library_panel(library_path or DEFAULT_LIBRARY, width, height, engine) if panel else None
    if not library.assets:
        raise SystemExit(_fail(f"{library_path}: the library has no assets"))
    _reset(width, height, engine)
    n = len(library.assets)
    cols = max(1, int(math.ceil(math.sqrt(n * 1.3))))
    rows = [library.assets[i:i + cols] for i in range(0, n, cols)]
    pitch_y = max(a.dimensions[1] for a in library.assets) + 3.2
    gap = 1.5
    lo = np.array([np.inf] * 3)
    hi = -lo
    for r, row in enumerate(rows):
        row_len = sum(a.dimensions[0] for a in row) + gap * (len(row) - 1)
        x = -row_len / 2
        for asset in row:
            mesh = load_asset_mesh(library, asset.id)
            v = np.asarray(mesh.vertices, dtype=np.float64)
            # Rows left to right, each vehicle's front to the right (+x).
            offset = np.array([x + asset.dimensions[0] / 2, -r * pitch_y, 0.0])
            x += asset.dimensions[0] + gap
            v = v + offset
            face_rgba = None
            fc = getattr(getattr(mesh, "visual", None), "face_colors", None)
            if fc is not None and len(fc) == len(mesh.faces):
                rgb = _srgb_to_linear(np.asarray(fc[:, :3], dtype=np.float64) / 255.0)
                face_rgba = np.concatenate([rgb, np.ones((len(rgb), 1))], axis=1)
            _mesh_object(asset.id, v, np.asarray(mesh.faces), BODY, face_rgba)
            _label(asset.id.split(".", 1)[-1], offset[0], offset[1] - asset.dimensions[1] / 2 - 1.0, 0.6)
            lo = np.minimum(lo, v.min(axis=0) - [0, pitch_y / 2, 0])
            hi = np.maximum(hi, v.max(axis=0))
    _ground(lo, hi)
    _camera_fit(lo, hi, elevation_deg=65.0, azimuth_deg=-90.0)
    _render(out, state)


def _library_panel(path: Path, width: int, height: int, engine: str) -> tuple[str, list]:
    """The Library panel after Load library (through its operator): the asset list, the active
    asset's box and its cleaning report."""
    import bpy

    import blender_addon
    from blender_addon.ops_library import cleaning_lines

    _reset(width, height, engine)
    blender_addon.register()
    try:
        bpy.ops.adv3d.library_load(filepath=str(path))
        lib = bpy.context.scene.adv3d.library
        lines: list = [f"{Path(lib.path).parent.name}/{Path(lib.path).name}: {len(lib.assets)} assets"]
        for item in list(lib.assets)[:13]:
            lines.append(f"{'[x]' if item.in_shape_space else '[  ]'} {item.asset_id[:30]:<31}{item.vehicle_class}")
        if len(lib.assets) > 13:
            lines.append(f"... {len(lib.assets) - 13} more ([x]: in the shape space)")
        item = lib.assets[lib.active_index]
        lines += [("head", item.asset_id), f"Size {item.length:.2f} x {item.width:.2f} x {item.height:.2f} m",
                  f"{item.triangle_count} triangles, licence {item.licence}", ("head", "Cleaning report")]
        lines += cleaning_lines(item.cleaning_report)[:8]
        lines += [("button", "Import vehicle file...")]
    finally:
        blender_addon.unregister()
    return "Adv3D  >  Library", lines


def render_sweep(space_path: Path | None, out: Path, dim: int, steps: int, width: int, height: int,
                 engine: str) -> None:
    """Shapes along one unit-vector dimension (others at 0.5), side by side, labelled."""
    from adv3d_runner.errors import Adv3dError
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

    space = ShapeSpace.load(space_path or DEFAULT_SHAPE_SPACE)
    if not 0 <= dim < space.dim:
        raise SystemExit(_fail(f"--dim must be in [0, {space.dim - 1}] (K={space.k} latents, then width, length)"))
    if steps < 2:
        raise SystemExit(_fail("--steps must be at least 2"))
    _reset(width, height, engine)
    names = [f"z{i + 1}" for i in range(space.k)] + ["width", "length"]
    x = 0.0
    lo = np.array([np.inf] * 3)
    hi = -lo
    for i, t in enumerate(np.linspace(0.0, 1.0, steps)):
        u = np.full(space.dim, 0.5)
        u[dim] = t
        try:
            v, f = space.decode_arrays(u)
        except Adv3dError as exc:
            print(f"skipping {names[dim]}={t:.2f}: {exc}", file=sys.stderr)
            continue
        # End to end along +x (each car's front to the right), seen from its right side.
        length_m = np.ptp(v[:, 0])
        if i:
            x += length_m / 2 + 1.5
        v = v + np.array([x, 0.0, 0.0])
        _mesh_object(f"{names[dim]}={t:.2f}", v, f, SWEEP)
        _label(f"{names[dim]} = {t:.2f}", x, -np.ptp(v[:, 1]) / 2 - 1.2, 0.5)
        lo = np.minimum(lo, v.min(axis=0) - [0, 2.0, 0])
        hi = np.maximum(hi, v.max(axis=0))
        x += length_m / 2
    if not np.isfinite(lo).all():
        raise SystemExit(_fail("no shape along the sweep has a surface"))
    _ground(lo, hi)
    _camera_fit(lo, hi, elevation_deg=30.0, azimuth_deg=-70.0)
    _render(out)


def render_shapes(space_path: Path | None, out: Path, unit: list[float] | None, width: int, height: int,
                  engine: str, panel: bool = False) -> None:
    """The Shape space panel in use: the space loaded and the sliders set through its operators,
    the preview vehicle it decoded (and the panel's sliders beside it with ``panel``)."""
    import bpy
    import numpy as np

    import blender_addon
    from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE
    from blender_addon import ops_shapes

    scene = _reset(width, height, engine)
    blender_addon.register()
    try:
        bpy.ops.adv3d.shapes_load(filepath=str(space_path or DEFAULT_SHAPE_SPACE))
        shapes = scene.adv3d.shapes
        if unit is not None:
            if len(unit) != shapes.k + 2:
                raise SystemExit(_fail(f"--u needs {shapes.k + 2} values (K={shapes.k} latents, width, length)"))
            ops_shapes.set_unit(shapes, np.asarray(unit, dtype=np.float64))
        ops_shapes.update_preview(scene)
        bpy.ops.adv3d.shapes_nearest()
        preview = ops_shapes.preview_object(scene, create=False)
        v = np.array([c.co for c in preview.data.vertices]) + np.array(preview.matrix_world.translation)
        f = np.array([p.vertices[:] for p in preview.data.polygons])
        bpy.data.objects.remove(preview)  # drawn again with a colour attribute
        _mesh_object("preview", v, f, SWEEP)
        lines: list = [Path(shapes.space_path).name, ("head", "Explained variance"),
                       *shapes.variance_text.split("  ")]
        lines += [("slider", f"z{i + 1}", shapes.latent[i]) for i in range(shapes.k)]
        lines += [("slider", "Width scale", shapes.width_scale), ("slider", "Length scale", shapes.length_scale),
                  f"Live: decode + mesh update {shapes.last_update_ms:.1f} ms",
                  ("button", "Random sample"), f"Nearest: {shapes.nearest_asset}", ("button", "Export shape"),
                  ("button", "Build shape space")]
    finally:
        blender_addon.unregister()
    lo, hi = v.min(axis=0), v.max(axis=0)
    _ground(lo, hi)
    _camera_fit(lo - [0.5, 0.5, 0.0], hi + [0.5, 0.5, 0.0], elevation_deg=25.0, azimuth_deg=-60.0)
    _render(out, ("Adv3D  >  Shape space", lines) if panel else None)


def render_scene(scene_path: Path, library_path: Path | None, out: Path, frame: int, width: int, height: int,
                 engine: str, panel: bool = False) -> None:
    """A scene loaded through the add-on's Scenes panel code, at one frame, around the ego."""
    import bpy

    import blender_addon
    from adv3d_runner.shapes.library import DEFAULT_LIBRARY, load_library
    from blender_addon import ops_scene

    scene = _reset(width, height, engine)
    blender_addon.register()
    lib_path = library_path or DEFAULT_LIBRARY
    library = load_library(lib_path) if Path(lib_path).exists() else None
    ops_scene.load_scene_objects(scene, str(scene_path), library)
    if not scene.frame_start <= frame <= scene.frame_end:
        raise SystemExit(_fail(f"--frame must be in [{scene.frame_start}, {scene.frame_end}]"))
    scene.frame_set(frame)
    colours = {"EGO": (0.1, 0.35, 0.9, 1.0), "ACTOR": (0.85, 0.55, 0.15, 1.0)}
    for obj in scene.objects:
        role = obj.adv3d.role
        if role in colours and obj.type == "MESH":
            # One colour attribute per mesh datablock (library meshes are shared between actors).
            mesh = obj.data
            if mesh.color_attributes.get("Col") is None:
                attr = mesh.color_attributes.new("Col", "FLOAT_COLOR", "CORNER")
                rgba = np.tile(np.asarray(colours[role], np.float32), (len(mesh.loops), 1))
                attr.data.foreach_set("color", rgba.ravel())
                mesh.color_attributes.active_color = attr
        elif role == "LANE":
            obj.data.bevel_depth = 0.06
            obj.data.materials.append(bpy.data.materials.new("lane"))
    ego = next(o for o in scene.objects if o.adv3d.role == "EGO")
    # A chase camera: 16 m behind the ego, 9 m up, looking 18 m ahead of it.
    from mathutils import Vector

    centre = np.array(ego.matrix_world.translation)
    yaw = ego.matrix_world.to_euler().z
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    cam_data = bpy.data.cameras.new("camera")
    cam_data.lens = 28.0
    cam_data.clip_end = 2000.0
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.location = centre - 16.0 * fwd + np.array([0.0, 0.0, 9.0])
    target = Vector((centre + 18.0 * fwd).tolist())
    cam.rotation_euler = (target - cam.location).to_track_quat("-Z", "Y").to_euler()
    sc = scene.adv3d.scene
    lines: list = [f"{Path(scene_path).name}", ("head", f"Scene {sc.scene_id}"),
                   f"frame {frame} of {scene.frame_end + 1} ({scene.render.fps} fps)",
                   f"{sum(o.adv3d.role == 'ACTOR' for o in scene.objects)} actors, "
                   f"{sum(o.adv3d.role == 'LANE' for o in scene.objects)} lanes",
                   ("button", "Export scene"), ("head", "Attack this scene")]
    lines += [f"{name}: {getattr(sc, 'attack_' + name)}" for name in ("algo", "budget", "seconds", "autonomy")]
    lines += [("button", "Attack this scene"), "Edit keyframes / assets, then Export"]
    blender_addon.unregister()
    _render(out, ("Adv3D  >  Scenes", lines) if panel else None)


def render_review(run_path: Path, replay: str | None, out: Path, frame: int | None, width: int, height: int,
                  engine: str, panel: bool = False) -> None:
    """One frame of a run bundle's replay, loaded through the Review panel code: ego (blue),
    actors (grey, the adversarial shape red), LiDAR points, detection boxes with scores, the
    predicted trajectories and the plan, from a camera behind and above the ego."""
    import bpy
    from mathutils import Vector

    import blender_addon
    from blender_addon import ops_review

    found = ops_review.find_replays(run_path)
    chosen = [p for label, p in found if replay is None or replay in label or replay == str(p)]
    if not chosen:
        raise SystemExit(_fail(f"--replay {replay!r} matches none of: " + ", ".join(label for label, _ in found)))
    scene = _reset(width, height, engine)
    if engine != "eevee":
        shading = scene.display.shading
        shading.color_type = "MATERIAL"  # the review's materials: per-object colours, heat-map bins
        shading.show_cavity = False  # cavity speckles the point cloud and the boxes
        shading.show_specular_highlight = False
    blender_addon.register()
    counts = ops_review.load_review(scene, chosen[0])
    frame = counts["frames"] // 2 if frame is None else frame
    if not 0 <= frame < counts["frames"]:
        raise SystemExit(_fail(f"--frame must be in [0, {counts['frames'] - 1}]"))
    scene.frame_set(frame)
    objs = bpy.data.objects  # colours, line widths and box edges are the Review panel's own
    lo, hi = np.array([-1e3, -1e3, 0.0]), np.array([1e3, 1e3, 0.0])
    _ground(lo, hi)
    objs["ground"].color = (0.85, 0.86, 0.88, 1.0)
    if not objs["ground"].data.materials:
        ground = bpy.data.materials.new("ground")
        ground.diffuse_color = (0.85, 0.86, 0.88, 1.0)
        objs["ground"].data.materials.append(ground)
    ego = objs["review ego"]
    centre = np.array(ego.matrix_world.translation)
    yaw = ego.matrix_world.to_euler().z
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    cam_data = bpy.data.cameras.new("camera")
    cam_data.lens = 38.0
    cam_data.clip_end = 2000.0
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    # Behind, above and a little to the right of the ego, looking at the road ahead.
    side = np.array([-fwd[1], fwd[0], 0.0])
    cam.location = centre - 20.0 * fwd - 7.0 * side + np.array([0.0, 0.0, 15.0])
    target = Vector((centre + 14.0 * fwd).tolist())
    cam.rotation_euler = (target - cam.location).to_track_quat("-Z", "Y").to_euler()
    rv = scene.adv3d.review
    data = ops_review.review.data_of(scene)
    dets = data.detections[frame] if data is not None and data.detections is not None else np.zeros((0, 7))
    lines: list = [f"{Path(run_path).name}", [label for label, p in found if p == chosen[0]][0],
                   ("button", "Load review"), ("head", f"Frame {frame} of {counts['frames']}"),
                   f"{counts['actors']} actors ({counts['adversarial']} adversarial, red)",
                   f"{len(data.points[frame]) if data is not None and data.points else 0} LiDAR points",
                   f"{len(dets)} detections, scores " + " ".join(f"{v:.2f}" for v in sorted(dets[:, 6])[::-1][:4]),
                   f"{len(data.predictions[frame]) if data is not None else 0} predicted trajectories (violet)",
                   "plan (yellow)", "Scrub the timeline to step through", ("head", "Legend"),
                   *(text for text, _ in ops_review.review.LEGEND),
                   f"replay sha256 {rv.key.rsplit(':', 1)[-1][:12]}..."]
    _render(out, ("Adv3D  >  Review", lines) if panel else None)
    blender_addon.unregister()


def _fail(message: str) -> int:
    print(f"adv3d render: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m blender_addon.render")
    parser.add_argument("--what", choices=("library", "sweep", "shapes", "scene", "review"), required=True)
    parser.add_argument("--panel", action="store_true", help="the panel's state in a column beside the picture")
    parser.add_argument("--u", default=None, help="shapes: unit vector z1,..,zK,width,length (default: 0.5s)")
    parser.add_argument("--scene", type=Path, default=None)
    parser.add_argument("--frame", type=int, default=None)
    parser.add_argument("--run", type=Path, default=None)
    parser.add_argument("--replay", default=None)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--library", type=Path, default=None)
    parser.add_argument("--space", type=Path, default=None)
    parser.add_argument("--dim", type=int, default=0)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--size", default="1280x720")
    parser.add_argument("--engine", choices=("workbench", "eevee"), default="workbench")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    from adv3d_runner.errors import Adv3dError

    try:
        if args.what == "library":
            render_library(args.library, args.out, width, height, args.engine, args.panel)
        elif args.what == "shapes":
            unit = [float(v) for v in args.u.split(",")] if args.u else None
            render_shapes(args.space, args.out, unit, width, height, args.engine, args.panel)
        elif args.what == "scene":
            if args.scene is None:
                return _fail("--what scene needs --scene FILE")
            render_scene(args.scene, args.library, args.out, args.frame or 0, width, height, args.engine, args.panel)
        elif args.what == "review":
            if args.run is None:
                return _fail("--what review needs --run BUNDLE (or a replay file)")
            render_review(args.run, args.replay, args.out, args.frame, width, height, args.engine, args.panel)
        else:
            render_sweep(args.space, args.out, args.dim, args.steps, width, height, args.engine)
    except Adv3dError as exc:
        return _fail(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
