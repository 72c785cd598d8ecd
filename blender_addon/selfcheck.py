"""Install a built extension zip into a throw-away Blender user folder and register it.

Run as a script in a child process (``adv3d blender build`` does it)::

    python blender_addon/selfcheck.py dist/adv3d-0.1.0-linux_x64.zip

It goes through Blender's own installer (``extensions.package_install_files``: unpacks the zip,
installs the listed wheels into the extensions' site-packages, enables the add-on), with the
packages the extension must bring itself (adv3d_runner, trimesh, skimage, lazy_loader) hidden
from the surrounding Python environment, so a wheel missing from the zip fails here. Exit
status 0 = OK, 2 = a problem (message on stderr).
"""
from __future__ import annotations

import importlib.machinery
import os
import sys
import tempfile
from pathlib import Path

# Top-level packages the extension must ship (looked up only outside this Python environment).
MUST_SHIP = ("adv3d_runner", "trimesh", "skimage", "lazy_loader")
# Packages a stock Blender lacks and the extension does not ship: blocked outright, so an
# add-on code path that needs them fails here rather than on a user's machine.
NOT_IN_BLENDER = ("scipy", "igl", "embreex", "torch")
EXPECTED_OPERATORS = ("library_load", "library_save", "shapes_load", "shapes_random", "scene_load", "scene_export",
                      "review_load", "review_clear")


class _HideEnvironment:
    """Meta-path finder that resolves ``MUST_SHIP`` packages only under ``allowed`` folders."""

    def __init__(self, allowed: str):
        self.allowed = allowed

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in NOT_IN_BLENDER:
            raise ImportError(f"{name} is not available in a stock Blender", name=name)
        if name.split(".")[0] not in MUST_SHIP or "." in name:
            return None
        search = [p for p in sys.path if p and os.path.abspath(p).startswith(self.allowed)]
        spec = importlib.machinery.PathFinder.find_spec(name, search)
        if spec is None:
            raise ImportError(f"{name} is not shipped with the extension", name=name)
        return spec


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: selfcheck.py EXTENSION.zip", file=sys.stderr)
        return 2
    zip_path = Path(argv[0]).resolve()
    with tempfile.TemporaryDirectory(prefix="adv3d-selfcheck-") as tmp:
        os.environ["BLENDER_USER_RESOURCES"] = tmp  # must be set before bpy starts
        for name in list(sys.modules):
            if name.split(".")[0] in MUST_SHIP + NOT_IN_BLENDER:
                del sys.modules[name]
        sys.meta_path.insert(0, _HideEnvironment(os.path.abspath(tmp)))
        import bpy

        result = bpy.ops.extensions.package_install_files(
            filepath=str(zip_path), repo="user_default", enable_on_install=True)
        if "FINISHED" not in result:
            print(f"{zip_path}: Blender refused to install the extension ({result})", file=sys.stderr)
            return 2
        problems = []
        if not hasattr(bpy.types.Scene, "adv3d"):
            problems.append("Scene.adv3d property group not registered")
        for op in EXPECTED_OPERATORS:
            if not hasattr(bpy.ops.adv3d, op) or getattr(bpy.ops.adv3d, op).idname() != f"ADV3D_OT_{op}":
                problems.append(f"operator adv3d.{op} missing")
        # The operators import the runner lazily; import its numpy-only parts now.
        try:
            import adv3d_runner.scene.schema  # noqa: F401
            import adv3d_runner.shapes.library  # noqa: F401
            import adv3d_runner.shapes.mesh_io  # noqa: F401  (review: adversarial glb shapes)
            import adv3d_runner.sim.replay  # noqa: F401  (review: replay files)
            import skimage.measure  # noqa: F401
            import trimesh  # noqa: F401
            from skimage.measure import marching_cubes  # noqa: F401
            problems += _decode_check()
        except ImportError as exc:
            problems.append(f"import failed inside Blender: {exc}")
        else:
            import adv3d_runner

            if not os.path.abspath(adv3d_runner.__file__).startswith(os.path.abspath(tmp)):
                problems.append(f"adv3d_runner came from {adv3d_runner.__file__}, not from the extension")
        if "torch" in sys.modules:
            problems.append("the add-on imported torch")
        import addon_utils

        addon_utils.disable("bl_ext.user_default.adv3d")
        if hasattr(bpy.types.Scene, "adv3d"):
            problems.append("unregister left Scene.adv3d behind")
        if problems:
            print(f"{zip_path}: " + "; ".join(problems), file=sys.stderr)
            return 2
    print(f"{zip_path}: installed, registered and unregistered cleanly")
    return 0


def _decode_check() -> list[str]:
    """Decode a two-part field (a body and a crumb) with the extension's own packages."""
    import numpy as np

    from adv3d_runner.shapes.decode import extract_surface
    from adv3d_runner.shapes.sdf import GridSpec

    grid = GridSpec(resolution=32, extent_m=6.0, ground_z=-0.2)
    axis = np.linspace(-0.5, 0.5, 32)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    body = np.sqrt(x**2 + y**2 + z**2) - 0.3
    crumb = np.sqrt((x - 0.42) ** 2 + y**2 + z**2) - 0.04
    vertices, faces = extract_surface(np.minimum(body, crumb).astype(np.float32), grid)
    if len(faces) == 0 or not np.isfinite(vertices).all():
        return ["decoding a test field inside Blender gave no surface"]
    return []


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
