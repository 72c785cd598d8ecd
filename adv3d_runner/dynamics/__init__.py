"""Ground floor: vehicle and traffic dynamics (kinematic bicycle, IDM/MOBIL).

Both the scene generator (traffic for the logs) and the planner and simulator (ego motion,
reactive actors) use these, so they sit below every layer that does. See docs/architecture.md.
"""
