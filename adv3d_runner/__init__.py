"""adv3d runner: headless shape space, scenes, LiDAR, autonomy and attacks.

Never imports bpy. See docs/architecture.md for the layers, the data flow and the contracts.
"""
__version__ = "0.1.0"
