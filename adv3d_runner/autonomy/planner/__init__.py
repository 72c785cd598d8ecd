"""Sampling-based lane-relative planner (nuPlan PDM-Closed style): proposals + named costs.

* corridors       current / left / right lane chains as stacked, uniformly sampled arrays,
  built every frame from the scene's lane map (:mod:`adv3d_runner.scene.corridor`,
  :class:`adv3d_runner.scene.lanemap.LaneMap`, handed over by ``reset(lane_map)``)
* :mod:`.proposals` candidates = lanes x lateral offsets x target speeds, rolled out on the
  kinematic bicycle (pure pursuit + IDM)
* :mod:`.costs`     named, separately testable cost terms
* :mod:`.scorer`    weighted sum with a per-term breakdown
* :mod:`.planner`   :class:`SamplingPlanner`
"""
from .planner import PlannerConfig, SamplingPlanner, forecast_from
from .proposals import ActorForecast, ProposalConfig
from .scorer import CostWeights, ScoreTable

__all__ = ["SamplingPlanner", "PlannerConfig", "ProposalConfig", "CostWeights", "ScoreTable", "ActorForecast",
           "forecast_from"]
