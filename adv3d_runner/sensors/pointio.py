"""LiDAR points on disk (binary PLY) and as a bird's-eye picture.

PLY layout (documented in docs/formats.md, "LiDAR points (PLY)"): binary little-endian, one
``vertex`` element with ``x y z intensity`` (float32, ego frame), ``ring`` (uint16), ``label``
(int32: actor id, -1 = background) and ``sensor`` (uint8); header comments carry the format
name and version, the scene id, frame and the ego pose.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FileFormatError
from ..fileio import atomic_path
from .lidar import LidarFrame

FORMAT = "adv3d-lidar-points"
VERSION = 1
_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2"),
                   ("label", "<i4"), ("sensor", "u1")])
_PLY_TYPES = {"<f4": "float", "<u2": "ushort", "<i4": "int", "|u1": "uchar"}


def frame_labels_as_ids(frame: LidarFrame) -> np.ndarray:
    """(N,) int32 label per point: the actor's id where ids are integers (scene actors), else
    the actor's index; -1 for background."""
    try:
        table = np.array([int(a) for a in frame.actor_ids] + [-1], dtype=np.int32)
    except (TypeError, ValueError):
        table = np.append(np.arange(len(frame.actor_ids), dtype=np.int32), np.int32(-1))
    return table[np.where(frame.label >= 0, frame.label, len(frame.actor_ids))]


def write_points_ply(path: str | Path, frame: LidarFrame, *, meta: dict | None = None) -> None:
    """Write a frame's points as binary PLY, atomically.

    Args:
        path: target file.
        frame: the points (ego frame).
        meta: extra ``key value`` header comments (scene id, frame, ego pose, sensor names).
    """
    rec = np.empty(len(frame), dtype=_DTYPE)
    for j, name in enumerate(("x", "y", "z", "intensity")):
        rec[name] = frame.points[:, j]
    rec["ring"] = frame.ring
    rec["label"] = frame_labels_as_ids(frame)
    rec["sensor"] = frame.sensor
    lines = ["ply", "format binary_little_endian 1.0", f"comment format {FORMAT}", f"comment version {VERSION}"]
    for key, value in (meta or {}).items():
        text = " ".join(str(v) for v in value) if isinstance(value, (list, tuple, np.ndarray)) else str(value)
        lines.append(f"comment {key} {text}".replace("\n", " "))
    lines.append(f"element vertex {len(rec)}")
    for name in _DTYPE.names:
        lines.append(f"property {_PLY_TYPES[_DTYPE[name].str]} {name}")
    lines.append("end_header")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(("\n".join(lines) + "\n").encode("ascii"))
            fh.write(rec.tobytes())


def read_points_ply(path: str | Path) -> tuple[np.ndarray, dict]:
    """Read a file written by :func:`write_points_ply`.

    Returns:
        (records, meta): structured (N,) array with fields x, y, z, intensity, ring, label,
        sensor; and the header comments as a dict of strings.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(path, "$", "a readable PLY file", str(exc)) from None
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise FileFormatError(path, "header", "a PLY header ending in end_header")
    header = raw[:end].decode("ascii", "replace").splitlines()
    meta: dict[str, str] = {}
    count = None
    props = []
    for line in header:
        parts = line.split(" ", 2)
        if parts[0] == "comment" and len(parts) >= 2:
            meta[parts[1]] = parts[2] if len(parts) > 2 else ""
        elif parts[0] == "element" and len(parts) == 3 and parts[1] == "vertex":
            count = int(parts[2])
        elif parts[0] == "property":
            props.append(line.split()[-1])
        elif parts[0] == "format" and line != "format binary_little_endian 1.0":
            raise FileFormatError(path, "header.format", "binary_little_endian 1.0", line)
    if meta.get("format") != FORMAT:
        raise FileFormatError(path, "header.comment format", FORMAT, meta.get("format"))
    if meta.get("version") != str(VERSION):
        raise FileFormatError(path, "header.comment version", str(VERSION), meta.get("version"))
    if tuple(props) != _DTYPE.names:
        raise FileFormatError(path, "header.properties", " ".join(_DTYPE.names), " ".join(props))
    body = raw[end + len(b"end_header\n"):]
    if count is None or len(body) != count * _DTYPE.itemsize:
        raise FileFormatError(path, "vertex", f"{count} records of {_DTYPE.itemsize} bytes", f"{len(body)} bytes")
    return np.frombuffer(body, dtype=_DTYPE).copy(), meta


def draw_bev(path: str | Path, frame: LidarFrame, *, boxes: list[tuple[object, np.ndarray, np.ndarray]] = (),
             ego_dimensions=None, extent: float = 60.0, title: str = "") -> None:
    """Bird's-eye PNG of a frame in the ego frame (x to the right, y up).

    Args:
        path: PNG file (written atomically).
        frame: the points.
        boxes: (actor id, pose (3,) x, y, yaw in the ego frame, dims (3,) L, W, H) per actor.
        ego_dimensions: (L, W, H) of the ego, drawn at the origin.
        extent: half-size of the square view, metres.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ax.set_facecolor("black")
    xyz = frame.xyz
    bg = frame.label < 0
    if bg.any():
        # Grey by intensity, scaled to the frame's 99th percentile so dark asphalt stays visible.
        scale = max(float(np.percentile(frame.intensity[bg], 99)), 1e-6)
        shade = 0.25 + 0.75 * np.clip(frame.intensity[bg] / scale, 0.0, 1.0)
        ax.scatter(xyz[bg, 0], xyz[bg, 1], s=0.2, c=shade, cmap="gray", vmin=0, vmax=1, linewidths=0,
                   rasterized=True)
    cmap = plt.get_cmap("tab10")
    on = ~bg
    if on.any():
        ax.scatter(xyz[on, 0], xyz[on, 1], s=1.0, c=cmap(frame.label[on] % 10), linewidths=0, rasterized=True)
    index = {a: i for i, a in enumerate(frame.actor_ids)}
    for actor_id, pose, dims in boxes:
        corners = _box_corners(pose, dims)
        if np.abs(corners).min(axis=0).max() > extent * 1.2:
            continue
        colour = cmap(index.get(actor_id, 0) % 10)
        ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor=colour, linewidth=1.0))
        ax.text(pose[0], pose[1] + 0.5 * float(dims[1]) + 1.0, str(actor_id), color=colour, fontsize=7,
                ha="center", va="bottom", clip_on=True)
    if ego_dimensions is not None:
        ax.add_patch(Polygon(_box_corners(np.zeros(3), ego_dimensions), closed=True, fill=True, facecolor="red",
                             edgecolor="white", linewidth=1.0))
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, ego forward)")
    ax.set_ylabel("y (m, ego left)")
    ax.set_title(title or f"{len(frame)} points", fontsize=9)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _box_corners(pose, dims) -> np.ndarray:
    x, y, yaw = (float(v) for v in pose)
    half_l, half_w = 0.5 * float(dims[0]), 0.5 * float(dims[1])
    local = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])
    c, s = np.cos(yaw), np.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + [x, y]
