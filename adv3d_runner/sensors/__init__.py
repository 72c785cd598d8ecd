"""LiDAR sensor models and the Embree ray caster."""
