"""Stack variants for one-off looks (``bench/sanity.py --autonomy bench.stack_variants:NAME``).

* ``a_predictor_ft``: Autonomy-A with the predictor of ``assets/models/predictor-fresh-ft``
  (``bench/predictor_finetune.py --out runs/predictor-ft``, copied there; docs/benchmark.md) in
  place of the shipped one; its ``stack_info`` names the variant and carries the SHA-256 of
  those weights.
"""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FT_PREDICTOR = ROOT / "assets" / "models" / "predictor-fresh-ft"


def a_predictor_ft():
    """Autonomy-A with the fine-tuned predictor (see the module docstring)."""
    from adv3d_runner.autonomy.predictor import load_predictor
    from adv3d_runner.autonomy.stacks import own_stack

    stack = own_stack("A")
    stack.predictor = load_predictor(FT_PREDICTOR)
    digest = hashlib.sha256((FT_PREDICTOR / "weights.pt").read_bytes()).hexdigest()[:16]
    stack.stack_info = dataclasses.replace(stack.stack_info, name="A-predictor-ft",
                                           fingerprint=f"{stack.stack_info.fingerprint};predictor-ft={digest}")
    return stack
