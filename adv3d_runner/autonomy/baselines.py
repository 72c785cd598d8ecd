"""Non-learned baselines that share the learned models' interfaces.

:class:`ConstantVelocityPredictor` turns :class:`~.interface.Tracks` into
:class:`~.interface.Predictions` by extrapolating each track's Kalman velocity. It is the
reference a learned predictor must beat (issue 4: "minADE over 6 s beats a constant-velocity
baseline"), and lets the episode loop run before any model is trained.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .interface import DT, PREDICTION_STEPS, Predictions, Tracks


@dataclass(frozen=True)
class ConstantVelocityPredictor:
    """Constant-velocity extrapolation with K speed-scaled modes.

    Attributes:
        speed_factors: one mode per factor, each extrapolating ``factor x velocity`` (the first
            is plain constant velocity).
        probabilities: mode probabilities (same length, normalised on use).
        steps: horizon in steps of ``dt`` (60 = 6 s).
    """

    speed_factors: tuple[float, ...] = (1.0, 0.8, 1.15)  # K = 3 modes, as the paper's stack
    probabilities: tuple[float, ...] = (0.6, 0.2, 0.2)
    steps: int = PREDICTION_STEPS
    dt: float = DT

    def __post_init__(self) -> None:
        if len(self.speed_factors) != len(self.probabilities) or not self.speed_factors:
            raise ValueError("need one probability per speed factor")

    def predict(self, tracks: Tracks) -> Predictions:
        """(N,) tracks -> Predictions with trajectories (N, K, steps, 2) at t + dt .. t + steps dt."""
        n = len(tracks)
        f = np.asarray(self.speed_factors, dtype=np.float64)
        p = np.asarray(self.probabilities, dtype=np.float64)
        t = np.arange(1, self.steps + 1) * self.dt  # (H,)
        vel = np.nan_to_num(np.asarray(tracks.velocities, dtype=np.float64).reshape(n, 2))
        xy = np.asarray(tracks.boxes, dtype=np.float64).reshape(n, 5)[:, :2]
        traj = xy[:, None, None, :] + f[None, :, None, None] * t[None, None, :, None] * vel[:, None, None, :]
        probs = np.broadcast_to(p / p.sum(), (n, len(p))).copy()
        return Predictions(tracks.ids.copy(), traj, probs, self.dt)

