"""Top and side silhouettes of library assets, to check by eye that each faces +x and stands
on z = 0 (front/back cannot be inferred from geometry, so a person must look once per pack)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def render_silhouettes(library, ids: list[str], output: str | Path, dpi: int = 80) -> Path:
    """Write a PNG grid: per asset a top view (x right, y up) and a side view (x right, z up).

    An arrow marks +x (the front), a line marks z = 0 and the origin is a cross, so a car
    facing backwards or floating is obvious.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from ..fileio import atomic_path
    from .library import load_asset_mesh

    n = len(ids)
    fig, axes = plt.subplots(n, 2, figsize=(9, 2.0 * n), squeeze=False)
    for row, asset_id in enumerate(ids):
        mesh = load_asset_mesh(library, asset_id)
        v = np.asarray(mesh.vertices)
        tri = v[mesh.faces]
        colours = np.asarray(mesh.visual.face_colors, dtype=float) / 255.0
        L = float(np.ptp(v[:, 0]))
        for col, (a, b, title) in enumerate(((0, 1, "top (x right, y up)"), (0, 2, "side (x right, z up)"))):
            ax = axes[row, col]
            # draw far faces first so near paint shows: sort by the hidden axis
            hidden = 2 if col == 0 else 1
            depth = tri[:, :, hidden].mean(axis=1)
            order = np.argsort(depth if col == 0 else -depth)
            ax.add_collection(PolyCollection(tri[order][:, :, [a, b]], facecolors=colours[order],
                                             edgecolors="none"))
            ax.axhline(0.0, color="k", lw=0.5)
            ax.plot([0], [0], "r+", ms=10)
            ax.annotate("", xy=(0.6 * L, 0), xytext=(0.2 * L, 0),
                        arrowprops={"arrowstyle": "->", "color": "red", "lw": 2})
            ax.set_xlim(-0.65 * L, 0.65 * L)
            lo, hi = v[:, b].min(), v[:, b].max()
            ax.set_ylim(min(lo, 0) - 0.3, hi + 0.3)
            ax.set_aspect("equal")
            ax.set_title(f"{asset_id}: {title}", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.tight_layout()
    output = Path(output)
    with atomic_path(output, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return output
