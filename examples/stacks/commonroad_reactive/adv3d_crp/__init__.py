"""Autonomy-C's planner side: CommonRoad's reactive planner (commonroad-reactive-planner) driven
from adv3d's lane map, ego state and obstacles. Runs in its own virtual environment (numpy 2);
imports nothing from adv3d_runner."""
from .planner import (CRPlanner, EgoInput, LaneInput, ObstacleInput, PlanResult, PlannerOptions)

__all__ = ["CRPlanner", "EgoInput", "LaneInput", "ObstacleInput", "PlanResult", "PlannerOptions"]
