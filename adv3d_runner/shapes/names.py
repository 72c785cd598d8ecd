"""Names the shape commands' parsers need, importing nothing (so ``adv3d --help`` stays fast);
:mod:`.sdf` re-exports them."""
from __future__ import annotations

#: SDF methods of :func:`adv3d_runner.shapes.sdf.sdf_volume` (its module docstring says how each works).
METHODS = ("winding", "winding-outward", "floodfill", "rayvote")
