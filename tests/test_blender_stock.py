"""The built extension in a stock Blender: every panel used through its operators.

The zip is built (``adv3d blender build``'s code), installed with Blender's own installer into a
throw-away user folder, and ``blender_addon/selfcheck.py --session`` imports a vehicle, builds
a shape space, moves the sliders, samples, exports, round-trips a scene and loads a review
(fixture data written here).

* fast (CI): in a child of this environment, with imports restricted to what a stock Blender has
  plus the extension's own site-packages (``selfcheck.StockBlender``): a package the zip does
  not ship fails the import;
* slow: in a fresh virtual environment holding only ``bpy==5.0.1`` and ``numpy<2`` (no system
  site-packages), installed from local wheels (``~/.cache/adv3d/stock-wheels``, downloaded once
  with pip when missing): nothing but the extension's wheels is there to lean on.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

STOCK_WHEELS = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "adv3d" / "stock-wheels"
STOCK_REQUIREMENTS = ("bpy==5.0.1", "numpy<2")


def write_session_data(root: Path) -> Path:
    """The files ``selfcheck.py --session`` uses: a library, a z-up OBJ vehicle with a licence, a
    scene and a run bundle with points."""
    import trimesh

    from test_blender_addon import CC0, _vehicle_mesh, make_library, make_scene
    from test_blender_review import make_replay, write_bundle

    make_library(root / "library")
    mesh = _vehicle_mesh(4.2, 1.8, 1.5, 0.5)
    assert isinstance(mesh, trimesh.Trimesh)
    mesh.export(root / "car.obj")  # z up, +x front (adv3d's frame)
    (root / "License.txt").write_text(CC0)
    make_scene(root / "scene.json")
    write_bundle(root / "run", make_replay(seed=5))
    return root


@pytest.fixture(scope="module")
def extension_zip(tmp_path_factory) -> Path:
    from adv3d_runner.blender_cli import build_extension, default_wheel_cache
    from adv3d_runner.errors import ConfigError

    try:  # the install check runs in the session below
        zips = build_extension(tmp_path_factory.mktemp("dist"), wheel_cache=default_wheel_cache(), bpy_check=False)
    except ConfigError as exc:
        if "pip download" in str(exc):
            pytest.skip(f"dependency wheels unavailable offline: {exc}")
        raise
    return zips[0]


def _session(python: str, zip_path: Path, data: Path, repo_root: Path, env: dict, cwd: Path) -> dict:
    proc = subprocess.run([python, str(repo_root / "blender_addon" / "selfcheck.py"), str(zip_path), "--session",
                           str(data)], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (proc.stderr[-3000:], proc.stdout[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_extension_zip_contents(extension_zip):
    """The zip: the add-on, its wheels (binary ones for cp311 and this platform), a manifest
    bounded to the Blender releases that run Python 3.11, and no development files."""
    import tomllib
    import zipfile

    from adv3d_runner.blender_cli import BLENDER_VERSION_MAX, check_manifest

    with zipfile.ZipFile(extension_zip) as zf:
        names = set(zf.namelist())
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        with zf.open(next(n for n in names if n.startswith("wheels/adv3d-"))) as fh:
            runner_names = set(zipfile.ZipFile(fh).namelist())
    assert check_manifest(manifest, names, "zip") == []
    assert manifest["blender_version_min"] == "4.2.0" and manifest["blender_version_max"] == BLENDER_VERSION_MAX
    assert manifest["platforms"] == ["linux-x64"]
    assert not {"selfcheck.py", "render.py"} & names
    for pkg in ("scipy", "libigl", "scikit_image", "trimesh"):
        assert any(n.startswith(f"wheels/{pkg}-") for n in names), pkg
    assert not any(n.startswith(("wheels/numpy", "wheels/torch", "wheels/tqdm", "wheels/bpy")) for n in names)
    # the runner wheel holds what the add-on runs, not the attack / autonomy / training code
    assert "adv3d_runner/sim/replay.py" in runner_names and "adv3d_runner/shapes/shape_space.py" in runner_names
    assert not any(n.startswith(("adv3d_runner/attack/", "adv3d_runner/autonomy/", "adv3d_runner/training/"))
                   for n in runner_names)
    # licensed as the extensions platform asks of add-ons, with the licence text and the note on
    # how it combines with the runner's MIT licence; starter data; embreex shipped
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"] and manifest["copyright"]
    assert {"LICENSE", "NOTICE.md", "starter/vehicles/library.json", "starter/shape_space/vehicles_64.npz",
            "starter/shape_space/realism_reference.npz"} <= names
    assert any(n.startswith("wheels/embreex-") for n in names)
    assert any("license" in p for p in check_manifest(dict(manifest, license=["SPDX:MIT"]), names, "zip"))
    from adv3d_runner.blender_cli import extension_sizes

    size = extension_sizes(extension_zip)
    assert size["zip"] < size["unpacked"] < size["site_packages"] + 20e6
    bad = dict(manifest, blender_version_max="6.0.0")
    assert any("blender_version_max" in p for p in check_manifest(bad, names, "zip"))
    bad = dict(manifest, platforms=["windows-x64"])
    assert any("does not load on windows-x64" in p for p in check_manifest(bad, names, "zip"))


def test_every_panel_works_with_only_what_a_stock_blender_has(extension_zip, tmp_path, repo_root):
    """Fast subset: this environment's Python, imports restricted to a stock Blender's plus the
    extension's (the repository and this venv's scipy / tqdm / igl are out of reach)."""
    data = write_session_data(tmp_path / "data")
    result = _session(sys.executable, extension_zip, data, repo_root, dict(os.environ), tmp_path)
    assert result["ok"]
    assert result["points_per_frame"][0] > 0


def _stock_python(root: Path) -> str:
    """A fresh venv with only bpy and numpy, from local wheels (downloaded once when missing)."""
    def have() -> bool:
        return any(STOCK_WHEELS.glob("bpy-5.0.1-*.whl")) and any(STOCK_WHEELS.glob("numpy-1.*.whl"))

    if not have():
        STOCK_WHEELS.mkdir(parents=True, exist_ok=True)
        got = subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--only-binary=:all:", "--dest",
                              str(STOCK_WHEELS), *STOCK_REQUIREMENTS], capture_output=True, text=True)
        if got.returncode != 0 or not have():
            pytest.skip(f"bpy / numpy wheels unavailable: {got.stderr.strip()[-300:]}")
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)  # no system site-packages
    python = str(venv / "bin" / "python")
    subprocess.run([python, "-m", "pip", "install", "--quiet", "--no-index", "--find-links", str(STOCK_WHEELS),
                    *STOCK_REQUIREMENTS], check=True)
    return python


@pytest.mark.slow
def test_every_panel_works_in_a_fresh_environment_with_only_bpy_and_numpy(extension_zip, tmp_path, repo_root):
    python = _stock_python(tmp_path)
    listed = subprocess.run([python, "-m", "pip", "list", "--format=json"], capture_output=True, text=True,
                            check=True)
    have = {p["name"].lower() for p in json.loads(listed.stdout)}
    assert not have & {"scipy", "trimesh", "scikit-image", "libigl", "tqdm", "torch", "adv3d"}, have
    data = write_session_data(tmp_path / "data")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    result = _session(python, extension_zip, data, repo_root, env, tmp_path)  # cwd outside the repository
    assert result["ok"] and result["numpy"].startswith("1.")
    shutil.rmtree(tmp_path / "venv", ignore_errors=True)  # ~1 GB


def test_no_build_for_a_platform_without_its_wheels(tmp_path):
    """A platform whose wheels cannot be had gets no zip: the build stops naming the missing
    wheel and the platform (here: an empty wheel cache, offline)."""
    from adv3d_runner.blender_cli import build_extension
    from adv3d_runner.errors import ConfigError

    with pytest.raises(ConfigError, match=r"no \S+ wheel for macos-arm64 in .*--offline"):
        build_extension(tmp_path / "out", platforms=["macos-arm64"], wheel_cache=tmp_path / "empty", offline=True,
                        bpy_check=False)
    assert not list((tmp_path / "out").glob("*.zip"))
