"""Ground floor: angles, frame changes and rotated BEV boxes (no project imports above errors).

See docs/architecture.md for the layers.
"""
