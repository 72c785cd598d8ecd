"""Seed ranges of the training and held-out scenes, importing nothing (the CLI's parsers use
them, so ``adv3d --help`` stays fast); :mod:`.detector_data` re-exports them."""
from __future__ import annotations

TRAIN_SEED0 = 100_000     # training scenes: TRAIN_SEED0 + [0, N)
VAL_SEED0 = 900_000       # held-out scenes (same split, disjoint seed range): VAL_SEED0 + [0, M)
