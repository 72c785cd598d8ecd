"""Static background geometry of a scene, built from its lane map: one triangle soup.

``background_mesh(scene)`` returns ``(vertices (V, 3) float64 m, faces (F, 3) int32,
surface_kind (F,) int8)`` in the scene's map frame (z up, road surface at z = 0):

* road surface: one strip per lane (``asphalt``), following the lane's centre line and width;
* shoulders: asphalt strips beyond the lanes that have no left / right neighbour;
* lane markings: thin painted strips (0.15 m wide) lying ``MARKING_Z`` = 5 mm above the road,
  dashed (3 m paint, 9 m gap) between neighbouring lanes and solid along the road edges. Real
  geometry (instead of a per-face texture) lets the LiDAR see paint by a first hit on the
  strip; 5 mm is far above float32 round-off after centring and below any range noise;
* ground: one large plane ``GROUND_Z`` = 5 cm below the road covering the map's bounding box
  plus ``background.ground_margin`` (grass / soil beyond the road, and gores between ramps);
* barriers: concrete barriers as a trapezoidal (Jersey-like) extrusion, guardrails as a
  W-beam band (0.45-0.75 m) on posts every 4 m;
* extra static meshes from ``background.meshes`` (files relative to the scene file).

``REFLECTIVITY[surface_kind]`` gives the diffuse reflectivity in [0, 1] for the LiDAR
intensity model; ``SURFACE_KINDS`` names the kinds. Triangle counts stay in the low thousands
per kilometre of road (one Embree scene per scene).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import MeshImportError
from . import lanes as lg
from .schema import Scene

SURFACE_KINDS = ("asphalt", "lane_paint", "concrete", "metal", "ground", "vegetation")
ASPHALT, LANE_PAINT, CONCRETE, METAL, GROUND, VEGETATION = range(6)
# Diffuse reflectivity per surface kind (fractions), typical 905 nm values: dark asphalt ~0.1,
# retro-reflective paint ~0.5, weathered concrete ~0.3, galvanised steel ~0.45 (diffuse part),
# dry grass / soil ~0.2-0.25.
REFLECTIVITY = np.array([0.10, 0.55, 0.30, 0.45, 0.20, 0.25], dtype=np.float64)

MARKING_Z = 0.005
MARKING_WIDTH = 0.15
DASH, GAP = 3.0, 9.0
GROUND_Z = -0.05
STEP = 20.0  # m, extra stations on long segments (every centre-line vertex is always kept)


class _Soup:
    def __init__(self) -> None:
        self.v: list[np.ndarray] = []
        self.f: list[np.ndarray] = []
        self.k: list[np.ndarray] = []
        self.n = 0

    def add(self, vertices: np.ndarray, faces: np.ndarray, kind: int) -> None:
        if len(faces) == 0:
            return
        self.v.append(np.asarray(vertices, dtype=np.float64))
        self.f.append(np.asarray(faces, dtype=np.int64) + self.n)
        self.k.append(np.full(len(faces), kind, dtype=np.int8))
        self.n += len(vertices)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not self.v:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int8)
        return np.concatenate(self.v), np.concatenate(self.f).astype(np.int32), np.concatenate(self.k)


def _strip(left: np.ndarray, right: np.ndarray, z: float | tuple[float, float] = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Quad strip between two (P, 2) polylines; faces wound counter-clockwise seen from +z
    (left/right w.r.t. the travel direction). ``z`` may differ per side (walls)."""
    P = len(left)
    zl, zr = (z, z) if np.isscalar(z) else z
    verts = np.concatenate([np.c_[left, np.full(P, zl)], np.c_[right, np.full(P, zr)]])
    i = np.arange(P - 1)
    # right[i], right[i+1], left[i+1] and right[i], left[i+1], left[i]: CCW from above
    faces = np.concatenate([np.stack([P + i, P + i + 1, i + 1], 1), np.stack([P + i, i + 1, i], 1)])
    return verts, faces


def _lane_edges(centerline: np.ndarray, width: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Resampled centre line and its left/right edges; returns (s, centre, left, right)."""
    pts = lg.clean_polyline(centerline)
    if len(pts) < 2:
        return np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2))
    s_raw = lg.arc_length(pts)
    s = np.unique(np.concatenate([np.linspace(0.0, s_raw[-1], max(2, int(np.ceil(s_raw[-1] / step)) + 1)), s_raw]))
    s = s[np.concatenate([[True], np.diff(s) > 1e-3])]  # no near-duplicate stations
    centre = lg.point_at(pts, s)
    w = lg.width_at(centerline, width, s)
    normals = lg.vertex_normals(centre)
    return s, centre, centre + 0.5 * w[:, None] * normals, centre - 0.5 * w[:, None] * normals


def _marking(soup: _Soup, line: np.ndarray, dashed: bool) -> None:
    """Paint strip along ``line`` (P, 2); dashed lines are cut into DASH-long pieces."""
    line = lg.clean_polyline(line)
    if len(line) < 2:
        return
    total = lg.length(line)
    pieces = [(0.0, total)] if not dashed else [(a, min(a + DASH, total)) for a in np.arange(0.0, total, DASH + GAP)]
    for a, b in pieces:
        if b - a < 0.2:
            continue
        s = np.linspace(a, b, max(2, int(np.ceil((b - a) / STEP)) + 1))
        c = lg.point_at(line, s)
        n = lg.vertex_normals(c)
        v, f = _strip(c + 0.5 * MARKING_WIDTH * n, c - 0.5 * MARKING_WIDTH * n, MARKING_Z)
        soup.add(v, f, LANE_PAINT)


def _extrude(soup: _Soup, line: np.ndarray, profile: np.ndarray, kind: int) -> None:
    """Sweep a cross-section ``profile`` (Q, 2: lateral offset left +, height) along ``line``."""
    line = lg.clean_polyline(line)
    if len(line) < 2:
        return
    n = lg.vertex_normals(line)
    rings = [np.c_[line + off * n, np.full(len(line), h)] for off, h in profile]
    for a, b in zip(rings[:-1], rings[1:]):
        P = len(line)
        verts = np.concatenate([a, b])
        i = np.arange(P - 1)
        faces = np.concatenate([np.stack([i, i + 1, P + i + 1], 1), np.stack([i, P + i + 1, P + i], 1)])
        soup.add(verts, faces, kind)


def _box(center: np.ndarray, heading: float, size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Axis box (sides + top, no bottom) standing on z=0."""
    L, W, H = size
    c, s = np.cos(heading), np.sin(heading)
    local = np.array([[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]])
    xy = center + local @ np.array([[c, s], [-s, c]])
    verts = np.concatenate([np.c_[xy, np.zeros(4)], np.c_[xy, np.full(4, H)]])
    faces = []
    for i in range(4):
        j = (i + 1) % 4
        faces += [[i, j, 4 + j], [i, 4 + j, 4 + i]]
    faces += [[4, 5, 6], [4, 6, 7]]
    return verts, np.array(faces)


def _guardrail(soup: _Soup, line: np.ndarray, height: float) -> None:
    line = lg.clean_polyline(line)
    if len(line) < 2:
        return
    top = height
    bottom = max(0.05, height - 0.31)  # a W-beam is about 0.31 m tall
    _extrude(soup, line, np.array([[0.0, bottom], [0.0, top]]), METAL)
    total = lg.length(line)
    for pose in lg.pose_at(line, np.arange(0.0, total + 1e-9, 4.0)):
        v, f = _box(pose[:2], float(pose[2]), (0.15, 0.15, bottom + 0.1))
        soup.add(v, f, METAL)


def background_mesh(scene: Scene, scene_dir: str | Path | None = None, step: float = STEP) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle soup of the static background (see module docstring).

    Args:
        scene: the scene.
        scene_dir: folder the scene file lives in, to resolve ``background.meshes`` files
            (required only when the scene lists extra meshes).
        step: longitudinal resolution (m) of the strips.
    Returns:
        vertices (V, 3) float64 m, faces (F, 3) int32, surface_kind (F,) int8 indexing
        ``SURFACE_KINDS`` / ``REFLECTIVITY``.
    """
    soup = _Soup()
    bg = scene.background
    all_pts = []
    for lane in scene.lanes:
        s, centre, left, right = _lane_edges(lane.centerline, lane.width, step)
        if len(s) < 2:
            continue  # a lane that collapses to a point has no surface
        all_pts += [left, right]
        v, f = _strip(left, right)
        soup.add(v, f, ASPHALT)
        n = lg.vertex_normals(centre)
        if lane.left is None:
            if bg.shoulder_left > 0:
                v, f = _strip(left + bg.shoulder_left * n, left)
                soup.add(v, f, ASPHALT)
                all_pts.append(left + bg.shoulder_left * n)
            if bg.lane_markings:
                _marking(soup, left - 0.5 * MARKING_WIDTH * n, dashed=False)
        elif bg.lane_markings:
            _marking(soup, left, dashed=True)  # each internal line drawn once: by the right lane
        if lane.right is None:
            if bg.shoulder_right > 0:
                v, f = _strip(right, right - bg.shoulder_right * n)
                soup.add(v, f, ASPHALT)
                all_pts.append(right - bg.shoulder_right * n)
            if bg.lane_markings:
                _marking(soup, right + 0.5 * MARKING_WIDTH * n, dashed=False)
    for barrier in bg.barriers:
        all_pts.append(barrier.polyline)
        if barrier.kind == "concrete":
            h = barrier.height
            profile = np.array([[-0.30, 0.0], [-0.20, 0.25], [-0.08, h], [0.08, h], [0.20, 0.25], [0.30, 0.0]])
            _extrude(soup, barrier.polyline, profile, CONCRETE)
        else:
            _guardrail(soup, barrier.polyline, barrier.height)
    if bg.meshes:
        _static_meshes(soup, scene, scene_dir)
    if all_pts:
        pts = np.concatenate(all_pts)
        lo = pts.min(axis=0) - bg.ground_margin
        hi = pts.max(axis=0) + bg.ground_margin
        v = np.array([[lo[0], lo[1], GROUND_Z], [hi[0], lo[1], GROUND_Z], [hi[0], hi[1], GROUND_Z], [lo[0], hi[1], GROUND_Z]])
        soup.add(v, np.array([[0, 1, 2], [0, 2, 3]]), GROUND)
    return soup.result()


def _static_meshes(soup: _Soup, scene: Scene, scene_dir: str | Path | None) -> None:
    import trimesh

    from ..fileio import resolve_inside
    from ..shapes.mesh_io import check_mesh_file

    kinds = {name: i for i, name in enumerate(SURFACE_KINDS)}
    for i, item in enumerate(scene.background.meshes):
        if scene_dir is None:
            raise MeshImportError(f"scene {scene.id} lists background mesh {item.file!r}: pass scene_dir to resolve it")
        # the file stays inside the scene's folder, symlinks included (the loader checked the letters)
        path = resolve_inside(scene_dir, item.file, file=f"scene {scene.id}", field=f"$.background.meshes[{i}].file",
                              inside="the scene's folder")
        check_mesh_file(path)
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:  # trimesh raises many types for bad files
            raise MeshImportError(f"{path}: cannot load background mesh ({exc})") from None
        x, y, z, yaw = item.pose
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        soup.add(np.asarray(mesh.vertices, dtype=np.float64) @ R.T + [x, y, z], np.asarray(mesh.faces), kinds.get(item.surface, CONCRETE))


def reflectivity(surface_kind: np.ndarray) -> np.ndarray:
    """Per-face reflectivity (F,) float64 from ``surface_kind`` (F,)."""
    return REFLECTIVITY[np.asarray(surface_kind, dtype=np.int64)]
