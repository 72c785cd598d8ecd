"""Sampling-based lane-relative planner (nuPlan PDM-Closed style): proposals + named costs.

* :mod:`.corridor`  current / left / right lane chains as stacked, uniformly sampled arrays
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
