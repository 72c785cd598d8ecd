"""Names and bounds of the attack's options, importing nothing (the CLI's parsers use them, so
``adv3d --help`` stays fast; docs/performance.md). The modules that use them (:mod:`.config`,
:mod:`.search`, :mod:`.vertex_deform`, :mod:`.realism_constraints`) re-export them."""
from __future__ import annotations

from typing import Any

#: Attack modes: closed loop, open loop (then evaluated in closed loop), both (paper Table 1).
MODES = ("closed", "open", "both")
#: How a query becomes shapes: the shape space's latents (the paper's attack) or vertex
#: deformation of the actor's own mesh (the paper's baseline); see attack/shape_models.py.
SHAPE_MODELS = ("latent", "vd")
#: Largest --realism-weight and --max-mahalanobis: far above any use (costs are O(1e3), the
#: latent box lies within a Mahalanobis distance of a few units), low enough that a cost minus
#: W times a penalty stays finite.
MAX_REALISM_WEIGHT = 1e6
MAX_MAHALANOBIS = 1e6
#: Search algorithms (:mod:`.search`).
ALGORITHMS = ("bo", "random", "grid", "blendsearch", "bruteforce", "skopt")
#: Largest vertex-deformation bound accepted (metres): twice the paper's largest. A bound b can
#: change each dimension of the vehicle by up to 2 b, so at 2 m a 4.5 m car may become 8.5 m
#: long and 5.8 m wide: past that a query is no longer a deformed vehicle (docs/realism.md).
MAX_VD_BOUND = 2.0
#: Named settings of the realism knobs (``--realism-preset NAME``); each maps to the
#: AttackConfig fields it sets. ``realistic`` is the setting that bench/realism_sweep.py selects
#: (keep >= 75 % of the unconstrained gain with the best shapes' JSD inside the library's
#: leave-one-out range); see docs/realism.md for the evidence behind its values and their status.
PRESETS: dict[str, dict[str, Any]] = {
    "realistic": {"max_mahalanobis": None, "class_scales": True, "realism_weight": 300.0},
}
