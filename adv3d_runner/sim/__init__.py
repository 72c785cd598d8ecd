"""Kinematics, traffic model and the closed-/open-loop episode loop."""
