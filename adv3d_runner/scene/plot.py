"""Bird's-eye pictures of scenes (matplotlib; imported only when drawing)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .schema import Scene

_KIND_COLOURS = ("#4a4a4a", "#ffffff", "#b0a890", "#7fa7c9", "#9cc07a", "#5e8c3a")


def _box(x: float, y: float, yaw: float, L: float, W: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[L / 2, W / 2], [-L / 2, W / 2], [-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2]])
    return local @ np.array([[c, s], [-s, c]]) + [x, y]


def plot_scene(scene: Scene, out: str | Path, frame: int = 0, window: float | None = 120.0,
               background: bool = True, title: str | None = None) -> None:
    """Draw the background, lanes, the ego's whole logged path and every actor's box at
    ``frame`` (ego red, actors blue, synthetic poses dashed) into ``out`` (png/svg).

    Args:
        window: half size (m) of the view around the ego at ``frame``; None shows everything.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    fig, ax = plt.subplots(figsize=(10, 6), dpi=110)
    ax.set_facecolor(_KIND_COLOURS[4])
    if background:
        from .background import background_mesh
        v, f, k = background_mesh(scene)
        # draw order: ground, road, barriers, paint (the mesh itself separates them by height)
        priority = np.array([1, 3, 2, 2, 0, 0])[k]
        order = np.argsort(priority, kind="stable")
        tris = v[f[order]][:, :, :2]
        ax.add_collection(PolyCollection(tris, facecolors=[_KIND_COLOURS[i] for i in k[order]], edgecolors="face", linewidths=0.3))
    for lane in scene.lanes:
        ax.plot(lane.centerline[:, 0], lane.centerline[:, 1], color="#f0d000", lw=0.5, ls=":")
    ego = scene.ego_poses()
    ax.plot(ego[:, 0], ego[:, 1], color="red", lw=1.0, alpha=0.7)
    L, W, _ = scene.ego.dimensions
    ax.fill(*_box(*ego[frame], L, W).T, color="red", zorder=5)
    for actor in scene.actors:
        pose = scene.actor_poses(actor.id)[frame]
        if not np.isfinite(pose[0]):
            continue
        syn = scene.actor_synthetic(actor.id)[frame]
        poly = _box(*pose, actor.dimensions[0], actor.dimensions[1])
        ax.fill(*poly.T, facecolor="#2060c0", edgecolor="black", lw=0.5, ls="--" if syn else "-", zorder=4)
    ax.set_aspect("equal")
    if window is not None:
        cx, cy = ego[frame, :2]
        ax.set_xlim(cx - window, cx + window)
        ax.set_ylim(cy - 0.45 * window, cy + 0.45 * window)
    else:
        ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{scene.id}  frame {frame} (t = {frame * scene.dt:.1f} s)")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
