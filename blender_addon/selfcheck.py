# SPDX-License-Identifier: GPL-3.0-or-later
"""Install a built extension zip as a user of a stock Blender would, and use it.

Run as a script in a child process (``adv3d blender build`` runs the install check; the tests
run the session too)::

    python blender_addon/selfcheck.py dist/adv3d-0.1.0-linux_x64.zip [--session DATA_DIR]

It goes through Blender's own installer (``extensions.package_install_files``: unpacks the zip,
installs the listed wheels into the extensions' site-packages, enables the add-on) in a
throw-away Blender user folder. Imports are restricted to what a stock Blender has (the standard
library, bpy and Blender's own scripts, the packages Blender bundles: ``BLENDER_BUNDLED``) and
what the extension installed: a package found anywhere else (this environment's scipy, tqdm,
the repository's own adv3d_runner...) raises ImportError, so a code path that needs a package
the zip does not ship fails here rather than on a user's machine. Run with a Python that has
only bpy and numpy (``tests/test_blender_stock.py``) the restriction changes nothing.

``--session DATA_DIR`` then uses every panel through its operators on the files in DATA_DIR
(written by the tests: ``library/library.json``, ``car.obj``, ``scene.json``, ``run/``): import a
vehicle, build a shape space, move the sliders, sample, export, load and export a scene
(byte-identical), load a review and scrub it. It prints one JSON line of results.

Exit status 0 = OK, 2 = a problem (message on stderr).
"""
from __future__ import annotations

import importlib.machinery
import json
import os
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

#: Third-party packages a stock Blender's Python has (Blender 4.2-5.0 bundle these).
BLENDER_BUNDLED = ("numpy", "requests", "urllib3", "idna", "certifi", "charset_normalizer", "zstandard",
                   "Cython", "cython", "pyximport", "_distutils_hack", "pkg_resources", "setuptools", "pip")
#: Must come from the extension (checked after registering).
MUST_SHIP = ("adv3d_runner", "trimesh", "skimage", "lazy_loader", "igl", "scipy")
EXPECTED_OPERATORS = ("library_load", "library_save", "library_import", "shapes_load", "shapes_random",
                      "shapes_build", "shapes_export", "scene_load", "scene_export", "scene_attack",
                      "review_load", "review_clear")


class StockBlender:
    """Meta-path finder: top-level modules resolve only from the standard library, bpy (and
    Blender's scripts inside it), ``BLENDER_BUNDLED`` and the ``allowed`` folders (the
    extension's)."""

    def __init__(self, allowed: str):
        self.allowed = os.path.abspath(allowed)
        paths = sysconfig.get_paths()
        self.stdlib = {os.path.abspath(paths[k]) for k in ("stdlib", "platstdlib") if paths.get(k)}
        spec = importlib.machinery.PathFinder.find_spec("bpy")
        self.bpy_root = os.path.abspath(spec.submodule_search_locations[0]) if spec else None

    def _ok(self, loc: str) -> bool:
        loc = os.path.abspath(loc)
        if loc.startswith(self.allowed) or (self.bpy_root and loc.startswith(self.bpy_root)):
            return True
        parts = Path(loc).parts
        return any(loc.startswith(d) for d in self.stdlib) and "site-packages" not in parts \
            and "dist-packages" not in parts

    def find_spec(self, name, path=None, target=None):
        if "." in name or name in sys.builtin_module_names or name in BLENDER_BUNDLED or name == "bpy":
            return None  # submodules follow their package; the rest as normal
        # look only where a stock Blender with the extension would (skipping, e.g., the
        # repository on PYTHONPATH and this environment's site-packages)
        search = [p for p in (path or sys.path) if p and self._ok(p)]
        spec = importlib.machinery.PathFinder.find_spec(name, search)
        if spec is not None:
            return spec
        elsewhere = importlib.machinery.PathFinder.find_spec(name, path)
        if elsewhere is None:
            return None  # not found anywhere: the normal ModuleNotFoundError
        raise ImportError(f"{name} is not in a stock Blender and not shipped with the extension "
                          f"({elsewhere.origin})", name=name)


def install(zip_path: Path, user_dir: str) -> list[str]:
    """Install and enable the zip in a fresh Blender user folder; returns problems."""
    os.environ["BLENDER_USER_RESOURCES"] = user_dir  # must be set before bpy starts
    for name in list(sys.modules):
        if name.split(".")[0] in MUST_SHIP:
            del sys.modules[name]
    sys.meta_path.insert(0, StockBlender(user_dir))
    import bpy

    result = bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default",
                                                       enable_on_install=True)
    if "FINISHED" not in result:
        return [f"Blender refused to install the extension ({result})"]
    problems = []
    if not hasattr(bpy.types.Scene, "adv3d"):
        problems.append("Scene.adv3d property group not registered")
    for op in EXPECTED_OPERATORS:
        if not hasattr(bpy.ops.adv3d, op) or getattr(bpy.ops.adv3d, op).idname() != f"ADV3D_OT_{op}":
            problems.append(f"operator adv3d.{op} missing")
    if bpy.context.preferences.addons.get("bl_ext.user_default.adv3d") is None:
        problems.append("the add-on is not enabled")
    try:  # the operators import these lazily: import them now
        import adv3d_runner.scene.schema  # noqa: F401
        import adv3d_runner.shapes.library  # noqa: F401
        import adv3d_runner.shapes.mesh_io  # noqa: F401  (review: adversarial glb shapes)
        import adv3d_runner.shapes.shape_space  # noqa: F401
        import adv3d_runner.sim.replay  # noqa: F401  (review: replay files)
        import igl  # noqa: F401  (Build shape space)
        import scipy.ndimage  # noqa: F401  (Build shape space)
        import trimesh  # noqa: F401
        from skimage.measure import marching_cubes  # noqa: F401
        problems += _decode_check()
    except ImportError as exc:
        problems.append(f"import failed inside Blender: {exc}")
    else:
        for mod in ("adv3d_runner", "igl", "scipy", "skimage", "trimesh"):
            f = os.path.abspath(sys.modules[mod].__file__)
            if not f.startswith(os.path.abspath(user_dir)):
                problems.append(f"{mod} came from {f}, not from the extension")
    return problems


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


def session(data: Path) -> dict:
    """Every panel through its operators on the files in ``data``; returns timings (s) and
    counts, raises AssertionError / RuntimeError naming what failed."""
    import bpy
    import numpy as np

    out = data / "out"
    out.mkdir(exist_ok=True)
    ops = bpy.ops.adv3d
    scene = bpy.context.scene
    t = {}

    def timed(name, fn):
        t0 = time.perf_counter()
        result = fn()
        t[name] = round(time.perf_counter() - t0, 3)
        assert result == {"FINISHED"}, f"{name}: {result}"

    timed("library_load", lambda: ops.library_load(filepath=str(data / "library" / "library.json")))
    n0 = len(scene.adv3d.library.assets)
    timed("import_vehicle", lambda: ops.library_import(filepath=str(data / "car.obj"), vehicle_class="sedan",
                                                       axis_up="Z", axis_forward="X", asset_id="stock.car"))
    assert len(scene.adv3d.library.assets) == n0 + 1, "import did not add the asset"
    shapes = scene.adv3d.shapes
    shapes.space_path = str(out / "space.npz")
    shapes.build_resolution, shapes.build_k = 16, 2
    timed("build_shape_space", lambda: ops.shapes_build())
    assert (out / "space.npz").is_file() and shapes.k == 2
    preview = next(o for o in scene.objects if o.adv3d.role == "PREVIEW")
    before = len(preview.data.vertices), preview.data.vertices[0].co.copy()
    t0 = time.perf_counter()
    shapes.latent[0] = 0.95  # the slider's update decodes at once in background mode
    t["slider"] = round(time.perf_counter() - t0, 3)
    after = len(preview.data.vertices), preview.data.vertices[0].co.copy()
    assert after != before, "moving a slider did not change the preview"
    timed("random", lambda: ops.shapes_random())
    timed("nearest", lambda: ops.shapes_nearest())
    for ext in (".glb", ".obj", ".ply", ".stl"):
        timed(f"export{ext}", lambda: ops.shapes_export(filepath=str(out / f"shape{ext}")))
        assert (out / f"shape{ext}").stat().st_size > 1000
    timed("scene_load", lambda: ops.scene_load(filepath=str(data / "scene.json")))
    timed("scene_export", lambda: ops.scene_export(filepath=str(out / "scene.json")))
    assert (out / "scene.json").read_bytes() == (data / "scene.json").read_bytes(), "scene round trip differs"
    timed("review_load", lambda: ops.review_load(filepath=str(data / "run")))
    lidar = bpy.data.objects["review lidar"]
    counts = []
    for f in (2, 7):
        scene.frame_set(f)
        counts.append(len(lidar.data.vertices))
    assert counts[0] > 0 and counts[0] != counts[1], f"the review does not follow the timeline ({counts})"
    timed("review_clear", lambda: ops.review_clear())
    assert "torch" not in sys.modules, "the add-on imported torch"
    return {"ok": True, "seconds": t, "points_per_frame": counts,
            "adv3d_runner": os.path.dirname(sys.modules["adv3d_runner"].__file__), "numpy": np.__version__}


def main(argv: list[str]) -> int:
    args = list(argv)
    data = None
    if "--session" in args:
        i = args.index("--session")
        data = Path(args[i + 1]).resolve()
        del args[i:i + 2]
    if len(args) != 1:
        print("usage: selfcheck.py EXTENSION.zip [--session DATA_DIR]", file=sys.stderr)
        return 2
    zip_path = Path(args[0]).resolve()
    with tempfile.TemporaryDirectory(prefix="adv3d-selfcheck-") as tmp:
        problems = install(zip_path, tmp)
        if not problems and data is not None:
            try:
                print(json.dumps(session(data)))
            except (AssertionError, RuntimeError) as exc:
                problems.append(f"session: {exc}")
        import addon_utils
        import bpy

        addon_utils.disable("bl_ext.user_default.adv3d")
        if hasattr(bpy.types.Scene, "adv3d"):
            problems.append("unregister left Scene.adv3d behind")
        if problems:
            print(f"{zip_path}: " + "; ".join(problems), file=sys.stderr)
            return 2
    print(f"{zip_path}: installed, registered" + (", used" if data else "") + " and unregistered cleanly",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
