"""Stack variants for one-off looks (``bench/sanity.py --autonomy bench.stack_variants:NAME``).

* ``a_predictor_ft``: Autonomy-A with the predictor of ``assets/models/predictor-fresh-ft``
  (``bench/predictor_finetune.py --out runs/predictor-ft``, copied there; docs/benchmark.md) in
  place of the shipped one; its ``stack_info`` names the variant and carries the SHA-256 of
  those weights.
* ``a_predictor_anchored``: Autonomy-A with the anchored predictor
  (``python -m adv3d_runner.training.predictor_anchored``, docs/predictor.md), named and
  fingerprinted the same way; it was looked at from ``assets/models/predictor-anchored`` and is
  now the shipped ``assets/models/predictor`` (docs/benchmark.md), where this variant reads it.
* ``a_predictor_2026_shipped``: Autonomy-A with the predictor shipped before it
  (``assets/models/predictor-2026-shipped``).
"""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FT_PREDICTOR = ROOT / "assets" / "models" / "predictor-fresh-ft"
ANCHORED_PREDICTOR = ROOT / "assets" / "models" / "predictor"
OLD_PREDICTOR = ROOT / "assets" / "models" / "predictor-2026-shipped"


def _with_predictor(folder: Path, name: str, tag: str):
    """Autonomy-A with the predictor of ``folder``, its stack_info named ``name`` and its
    fingerprint extended by ``tag=<SHA-256 of the weights, 16 hex>``."""
    from adv3d_runner.autonomy.predictor import load_predictor
    from adv3d_runner.autonomy.stacks import own_stack

    stack = own_stack("A")
    stack.predictor = load_predictor(folder)
    digest = hashlib.sha256((folder / "weights.pt").read_bytes()).hexdigest()[:16]
    stack.stack_info = dataclasses.replace(stack.stack_info, name=name,
                                           fingerprint=f"{stack.stack_info.fingerprint};{tag}={digest}")
    return stack


def a_predictor_ft():
    """Autonomy-A with the fine-tuned predictor (see the module docstring)."""
    return _with_predictor(FT_PREDICTOR, "A-predictor-ft", "predictor-ft")


def a_predictor_anchored():
    """Autonomy-A with the anchored predictor (see the module docstring)."""
    return _with_predictor(ANCHORED_PREDICTOR, "A-predictor-anchored", "predictor-anchored")


def a_predictor_2026_shipped():
    """Autonomy-A with the predictor shipped before the anchored one (see the module docstring)."""
    return _with_predictor(OLD_PREDICTOR, "A-predictor-2026-shipped", "predictor-2026-shipped")
