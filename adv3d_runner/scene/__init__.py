"""Driving scenes: the scene file contract, generators and importers, background geometry.

Import what you need from the submodules; ``schema`` (numpy only) is re-exported here:
``load_scene``, ``save_scene``, ``Scene`` and the parts it is made of.
"""
from .schema import (  # noqa: F401
    Actor, Background, Barrier, Ego, Lane, Lidar, Scene, Source, StaticMesh, Track,
    default_sensors, load_scene, save_scene, scene_equal,
)
