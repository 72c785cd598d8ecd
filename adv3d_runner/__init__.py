"""adv3d runner: headless shape space, scenes, LiDAR, autonomy and attacks.

Never imports bpy. See DESIGN.md (shared) and docs/ for the architecture.
"""
__version__ = "0.1.0"
