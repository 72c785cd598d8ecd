"""Autonomy stacks under test: detector, tracker, predictor, planner."""
