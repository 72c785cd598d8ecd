"""``adv3d blender build`` / ``adv3d blender render``: package the Blender extension, render
previews headlessly.

The runner never imports bpy in its own process: building calls Blender's own extension tool
(``blender_ext.py``, shipped inside the ``bpy`` wheel, run as a plain Python script) and the
install/register check and the renders run in a child ``python -m blender_addon...`` process.

How adv3d_runner gets into Blender: the build packs it as a wheel made from this repository
(``adv3d-<version>-py3-none-any.whl``: the parts of ``adv3d_runner`` the add-on runs, no
dependency metadata), next to the wheels of the third-party packages the add-on's code paths
need and Blender lacks (trimesh; scikit-image for marching cubes, with lazy_loader and packaging;
libigl, scipy and embreex for Build shape space). numpy is excluded: Blender ships it. A
platform without one of these wheels gets no zip (the build stops naming the wheel). Wheels are pinned
to the versions installed here (the versions the tests ran with) and fetched once with
``pip download`` into a cache folder.
"""
from __future__ import annotations

import argparse
import base64
import hashlib
import importlib.metadata
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from . import argtypes as at
from .errors import ConfigError, Adv3dError
from .fileio import REPO_ROOT

ADDON_DIR = REPO_ROOT / "blender_addon"
EXTENSION_ID = "adv3d"

#: (distribution name, wheel file prefix) of the third-party packages the add-on imports
#: in-process: meshes need trimesh; decoding needs scikit-image's marching cubes (which imports
#: lazy_loader and packaging, not scikit-image's other dependencies); Build shape space needs
#: libigl (winding numbers, distances), scipy (ndimage: cavity fill) and embreex (the SDF's
#: visibility orientation of CAD panels casts rays, docs/shape_space.md). tqdm is not shipped: progress
#: bars are optional (``adv3d_runner.progress``).
EXTENSION_DEPENDENCIES = (
    ("trimesh", "trimesh"),
    ("scikit-image", "scikit_image"),
    ("lazy_loader", "lazy_loader"),
    ("packaging", "packaging"),
    ("libigl", "libigl"),
    ("scipy", "scipy"),
    ("embreex", "embreex"),
)

#: The Blender releases whose Python (3.11) the cp311 wheels load in: 4.2 (the first with
#: extensions) up to 5.0; Blender 5.1 moved to Python 3.13. The manifest's maximum is exclusive.
BLENDER_VERSION_MIN = "4.2.0"
BLENDER_VERSION_MAX = "5.1.0"

#: The parts of adv3d_runner the add-on runs (its wheel holds only these): the ground floor,
#: shapes, scene and the replay loader. Attack, autonomy, sensors and training (torch, Embree)
#: run in the runner process ("Attack this scene" starts it), never inside Blender.
RUNNER_PARTS = ("__init__.py", "errors.py", "fileio.py", "progress.py", "machine.py", "validate.py",
                "vehicle_classes.py", "geometry/", "dynamics/", "metrics/", "shapes/", "scene/",
                "sim/__init__.py", "sim/replay.py")

#: Blender platform name -> pip ``--platform`` tags (newest first; pip takes any of them).
PLATFORM_TAGS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    # embreex 4.4's arm64 wheel is tagged macOS 13: the arm64 zip needs macOS 13 or later
    "macos-arm64": ["macosx_14_0_arm64", "macosx_13_0_arm64", "macosx_12_0_arm64", "macosx_11_0_arm64"],
    "macos-x64": ["macosx_13_0_x86_64", "macosx_12_0_x86_64", "macosx_11_0_x86_64", "macosx_10_15_x86_64",
                  "macosx_10_13_x86_64", "macosx_10_9_x86_64"],
}

#: Licences the extensions platform takes for add-ons (they build on Blender's GPL Python API).
ADDON_LICENCES = ("SPDX:GPL-2.0-or-later", "SPDX:GPL-3.0-or-later")

# Files of blender_addon/ that go into the extension; the build-time self check and the
# headless renderer are tools of this repository, not of the add-on.
_ADDON_GLOBS = ("*.py", "blender_manifest.toml", "LICENSE", "NOTICE.md")
DEV_ONLY = ("selfcheck.py", "render.py")

#: Starter data packed under ``starter/`` (the add-on's defaults when no library or shape space
#: is set): the bundled library with its licences, the shipped shape space and its realism
#: reference (about 6 MB next to the wheels' 70 MB).
STARTER_FILES = (("assets/vehicles", "starter/vehicles"),
                 ("assets/shape_space/vehicles_64.npz", "starter/shape_space/vehicles_64.npz"),
                 ("assets/shape_space/realism_reference.npz", "starter/shape_space/realism_reference.npz"))


def default_wheel_cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "adv3d" / "wheels"


def host_platform() -> str:
    import platform

    machine = platform.machine().lower()
    arm = machine in {"arm64", "aarch64"}
    if sys.platform.startswith("linux"):
        return "linux-arm64" if arm else "linux-x64"
    if sys.platform == "darwin":
        return "macos-arm64" if arm else "macos-x64"
    return "windows-arm64" if arm else "windows-x64"


# --------------------------------------------------------------------------- CLI

def register(subparsers) -> None:
    parser = subparsers.add_parser("blender", help="build the Blender extension; render previews headlessly",
                                   description="Build the Blender extension zip or render previews with bpy.")
    sub = parser.add_subparsers(dest="blender_command", metavar="ACTION")

    b = sub.add_parser("build", help="build and validate the installable extension zip")
    b.add_argument("--out", type=Path, required=True, help="folder for the zip (created)")
    b.add_argument("--platform", action="append", choices=sorted(PLATFORM_TAGS), dest="platforms",
                   help="target platform (repeatable; default: this machine's); one zip per platform")
    b.add_argument("--wheel-cache", type=Path, default=None,
                   help=f"where downloaded wheels are kept (default {default_wheel_cache()})")
    b.add_argument("--offline", action="store_true", help="never run pip download: wheels must be in the cache")
    b.add_argument("--no-bpy-check", action="store_true",
                   help="skip installing the zip into a bpy child process and registering it")
    b.set_defaults(func=cmd_build)

    r = sub.add_parser("render", help="render the library grid, a latent sweep, a scene or a review frame to PNG")
    r.add_argument("--what", choices=("library", "sweep", "shapes", "scene", "review"), required=True)
    r.add_argument("--panel", action="store_true",
                   help="draw the panel's state (its list, sliders, settings) in a column beside the picture")
    r.add_argument("--u", default=None, type=_unit_text, help="shapes: unit vector z1,..,zK,width,length in [0, 1] (default 0.5s)")
    r.add_argument("--out", type=Path, required=True, help="PNG file to write")
    r.add_argument("--library", type=Path, default=None, help="library.json (default: the shipped library)")
    r.add_argument("--space", type=Path, default=None, help="shape-space .npz (default: the shipped one)")
    r.add_argument("--dim", type=at.count, default=0, help="sweep: latent dimension (0-based; K, K+1 = width, length)")
    r.add_argument("--steps", type=at.integer(1, 100), default=5, help="sweep: number of shapes")
    r.add_argument("--scene", type=Path, default=None, help="scene: scene file")
    r.add_argument("--frame", type=at.count, default=None, help="scene / review: frame to show (default 0 / the middle)")
    r.add_argument("--run", type=Path, default=None,
                   help="review: run bundle folder (runs/NAME), adv3d simulate output folder, or a replay file")
    r.add_argument("--replay", default=None,
                   help="review: which replay of the bundle, e.g. 'SCENE_ID / closed' or a scene id "
                        "(default: the first)")
    r.add_argument("--size", default="1280x720", type=_size, help="image size WxH in pixels (16 to 8192 each)")
    r.add_argument("--engine", choices=("workbench", "eevee"), default="workbench")
    r.set_defaults(func=cmd_render)

    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])


def cmd_build(args) -> int:
    from .progress import status

    zips = build_extension(args.out, platforms=args.platforms, wheel_cache=args.wheel_cache,
                           offline=args.offline, bpy_check=not args.no_bpy_check)
    for z in zips:
        size = extension_sizes(z)
        status(f"built {z} ({size['zip'] / 1e6:.1f} MB; unpacks to {size['unpacked'] / 1e6:.0f} MB, its wheels "
               f"install {size['site_packages'] / 1e6:.0f} MB into Blender's shared extension site-packages), "
               "validated")
    return 0


def _unit_text(text: str) -> str:
    """``--u``: comma-separated numbers in [0, 1] (passed on to the child as typed)."""
    from .argtypes import numbers

    numbers(0.0, 1.0)(text)
    return text


def _size(text: str) -> str:
    """``--size WxH``, 16 to 8192 pixels each."""
    try:
        w, h = (int(v, 10) for v in text.lower().split("x"))
    except ValueError:
        w = h = 0
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"expected WxH such as 1280x720 (16 to 8192 pixels each) (got {text!r})")
    return text


def cmd_render(args) -> int:
    w, h = (int(v, 10) for v in _size(args.size).lower().split("x"))
    if args.what == "sweep":  # --dim against the shape space's K + 2, before Blender starts
        from .errors import UsageError
        from .shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

        space = ShapeSpace.load(Path(args.space) if args.space else DEFAULT_SHAPE_SPACE)
        if args.dim >= space.dim:
            raise UsageError(f"--dim {args.dim}: expected 0..{space.dim - 1} (K={space.k} latents, then width, length)")
    # Paths mean what they mean where the user typed them: made absolute here, before the child
    # (which runs with the repository on its path) sees them.
    for name in ("out", "library", "space", "scene", "run"):
        if getattr(args, name, None) is not None:
            setattr(args, name, Path(getattr(args, name)).expanduser().absolute())
    cmd = [sys.executable, "-m", "blender_addon.render", "--what", args.what, "--out", str(args.out),
           "--size", f"{w}x{h}", "--engine", args.engine, "--dim", str(args.dim), "--steps", str(args.steps)]
    if args.panel:
        cmd += ["--panel"]
    if args.u:
        cmd += ["--u", args.u]
    if args.library:
        cmd += ["--library", str(args.library)]
    if args.space:
        cmd += ["--space", str(args.space)]
    if args.what == "scene":
        if args.scene is None:
            raise ConfigError("--what scene needs --scene FILE")
        cmd += ["--scene", str(args.scene), "--frame", str(args.frame or 0)]
    if args.what == "review":
        if args.run is None or not Path(args.run).exists():
            if args.run is not None:
                raise ConfigError(f"--run {args.run}: no such run bundle or replay file")
            raise ConfigError("--what review needs --run BUNDLE (a run bundle folder or a replay file)")
        cmd += ["--run", str(args.run)]
        if args.frame is not None:
            cmd += ["--frame", str(args.frame)]
        if args.replay:
            cmd += ["--replay", args.replay]
    _run_child(cmd, "render")
    from .progress import status

    status(f"wrote {args.out}")
    return 0


def _child_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO_ROOT) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _run_child(cmd: list[str], what: str, timeout: float = 600) -> str:
    """Run a bpy child process in the caller's folder; its exit status 2 carries a user-facing
    message on stderr."""
    proc = subprocess.run(cmd, env=_child_env(), capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
        msg = lines[-1] if lines else f"exit status {proc.returncode}"
        if proc.returncode == 2:
            raise Adv3dError(f"blender {what}: {msg}")
        raise RuntimeError(f"blender {what} child failed ({proc.returncode}):\n{proc.stderr[-4000:]}")
    return proc.stdout


# --------------------------------------------------------------------------- build

def runner_wheel(out_dir: Path) -> Path:
    """Write ``adv3d-<version>-py3-none-any.whl`` holding the ``adv3d_runner`` package.

    Written directly (zip + dist-info with RECORD hashes) rather than through a build backend:
    it is fast, needs no network, and the same sources give the same bytes.
    """
    from . import __version__

    name = f"adv3d-{__version__}-py3-none-any.whl"
    dist_info = f"adv3d-{__version__}.dist-info"
    files: list[tuple[str, bytes]] = []
    pkg = REPO_ROOT / "adv3d_runner"
    for path in sorted(pkg.rglob("*.py")):
        rel = path.relative_to(pkg).as_posix()
        if "__pycache__" in path.parts or not any(rel == p or (p.endswith("/") and rel.startswith(p))
                                                  for p in RUNNER_PARTS):
            continue
        files.append((path.relative_to(REPO_ROOT).as_posix(), path.read_bytes()))
    metadata = (f"Metadata-Version: 2.1\nName: adv3d\nVersion: {__version__}\n"
                "Summary: adv3d runner (packed for the Blender extension; dependencies ship as separate wheels)\n"
                "Requires-Python: >=3.11\n").encode()
    wheel = b"Wheel-Version: 1.0\nGenerator: adv3d blender build\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    files += [(f"{dist_info}/METADATA", metadata), (f"{dist_info}/WHEEL", wheel)]
    record = []
    for arc, data in files:
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        record.append(f"{arc},sha256={digest},{len(data)}")
    record.append(f"{dist_info}/RECORD,,")
    files.append((f"{dist_info}/RECORD", ("\n".join(record) + "\n").encode()))
    out = out_dir / name
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for arc, data in files:
            info = zipfile.ZipInfo(arc, date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, data)
    return out


def _wheel_matches(path: Path, prefix: str, version: str, platform: str) -> bool:
    parts = path.name[:-4].split("-")
    if len(parts) < 5 or parts[0].lower() != prefix.lower() or parts[1] != version:
        return False
    py, abi, plat = parts[-3], parts[-2], parts[-1]
    if plat == "any":
        return py.startswith("py3") or py == "cp311"
    if "cp311" not in py:
        return False
    return any(plat.split(".")[i] in PLATFORM_TAGS[platform] or _compatible_tag(plat.split(".")[i], platform)
               for i in range(len(plat.split("."))))


def _compatible_tag(tag: str, platform: str) -> bool:
    arch = {"linux-x64": "x86_64", "windows-x64": "amd64", "macos-arm64": "arm64", "macos-x64": "x86_64"}[platform]
    prefix = {"linux-x64": "manylinux", "windows-x64": "win", "macos-arm64": "macosx", "macos-x64": "macosx"}[platform]
    return tag.startswith(prefix) and tag.endswith(arch) or (platform == "macos-x64" and "universal2" in tag)


def fetch_wheels(platform: str, cache: Path, offline: bool = False) -> list[Path]:
    """The dependency wheels for ``platform`` (cp311), downloaded into ``cache`` if missing."""
    cache.mkdir(parents=True, exist_ok=True)
    found: list[Path] = []
    for dist, prefix in EXTENSION_DEPENDENCIES:
        try:
            version = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            raise ConfigError(f"{dist} is not installed here; install it so its version can be pinned") from None
        hits = sorted(p for p in cache.glob("*.whl") if _wheel_matches(p, prefix, version, platform))
        if not hits:
            if offline:
                raise ConfigError(f"no {dist}=={version} wheel for {platform} in {cache} (and --offline)")
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
                   "--python-version", "3.11", "--implementation", "cp", "--abi", "cp311", "--abi", "abi3",
                   "--abi", "none", "--dest", str(cache), "--quiet", f"{dist}=={version}"]
            for tag in PLATFORM_TAGS[platform]:
                cmd += ["--platform", tag]
            if platform != host_platform():
                pass  # --platform already restricts the choice
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode != 0:
                raise ConfigError(f"pip download {dist}=={version} for {platform} failed: "
                                  f"{proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}")
            hits = sorted(p for p in cache.glob("*.whl") if _wheel_matches(p, prefix, version, platform))
            if not hits:
                raise ConfigError(f"pip download gave no usable {dist}=={version} wheel for {platform}")
        found.append(hits[-1])
    return found


def _manifest_text(wheels: list[str], platforms: list[str]) -> str:
    """The source manifest with the ``wheels`` list and ``platforms`` filled in."""
    text = (ADDON_DIR / "blender_manifest.toml").read_text()
    for key, value in (("blender_version_min", BLENDER_VERSION_MIN), ("blender_version_max", BLENDER_VERSION_MAX)):
        if not re.search(rf'(?m)^{key} = "{re.escape(value)}"$', text):
            raise Adv3dError(f"blender_addon/blender_manifest.toml: expected {key} = \"{value}\" "
                             "(the Blender releases the cp311 wheels load in)")
    listed = "wheels = [\n" + "".join(f'  "./wheels/{w}",\n' for w in wheels) + "]\n"
    text, n = re.subn(r"(?ms)^wheels = \[.*?^\]\n", listed, text)
    if n != 1:
        raise Adv3dError("blender_addon/blender_manifest.toml: expected one `wheels = [...]` block")
    plat = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]\n"
    if re.search(r"(?m)^platforms = ", text):
        text = re.sub(r"(?m)^platforms = .*\n", plat, text)
    else:
        text = text.replace(listed, listed + plat)
    return text


def blender_ext_script() -> Path | None:
    """Blender's extension command-line tool inside the installed ``bpy`` wheel (not imported)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        for script in sorted(Path(loc).glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py")):
            return script
    return None


def build_extension(out: Path, platforms: list[str] | None = None, wheel_cache: Path | None = None,
                    offline: bool = False, bpy_check: bool = True) -> list[Path]:
    """Build one validated extension zip per platform into ``out``.

    Returns:
        the zip paths (``adv3d-<version>-<platform>.zip``).
    """
    from . import __version__
    from .progress import status

    platforms = platforms or [host_platform()]
    for p in platforms:
        if p not in PLATFORM_TAGS:
            raise ConfigError(f"--platform: no wheel tags known for {p!r} (known: {', '.join(PLATFORM_TAGS)})")
    cache = Path(wheel_cache) if wheel_cache else default_wheel_cache()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tool = blender_ext_script()
    zips = []
    for platform in platforms:
        with tempfile.TemporaryDirectory(prefix="adv3d-ext-") as tmp:
            stage = Path(tmp) / EXTENSION_ID
            (stage / "wheels").mkdir(parents=True)
            for pattern in _ADDON_GLOBS:
                for src in sorted(ADDON_DIR.glob(pattern)):
                    if src.name not in DEV_ONLY:
                        shutil.copy2(src, stage / src.name)
            _copy_starter(stage)
            wheels = [runner_wheel(stage / "wheels")]
            for whl in fetch_wheels(platform, cache, offline):
                wheels.append(Path(shutil.copy2(whl, stage / "wheels" / whl.name)))
            (stage / "blender_manifest.toml").write_text(_manifest_text([w.name for w in wheels], [platform]))
            target = out / f"{EXTENSION_ID}-{__version__}-{platform.replace('-', '_')}.zip"
            status(f"packing {target.name} ({len(wheels)} wheels)")
            if tool is not None:
                _blender_ext(tool, ["build", "--source-dir", str(stage), "--output-filepath", str(target)])
            else:  # no bpy here: zip the staged folder the way Blender's tool does
                _zip_dir(stage, target)
        # Installing is only possible on the platform the zip is for.
        validate_extension_zip(target, bpy_check=bpy_check and platform == host_platform())
        zips.append(target)
    return zips


def _copy_starter(stage: Path) -> None:
    """The starter library and shape space into ``stage/starter`` (skipped when this checkout
    lacks them; the add-on then simply has no defaults)."""
    for src, dst in STARTER_FILES:
        source = REPO_ROOT / src
        if source.is_dir():
            shutil.copytree(source, stage / dst, ignore=shutil.ignore_patterns("*.sh", "__pycache__", "*.md"))
        elif source.is_file():
            (stage / dst).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, stage / dst)


def extension_sizes(zip_path: Path) -> dict:
    """Sizes in bytes of a built extension: ``zip`` (the download, what the platform's upload
    limit applies to), ``unpacked`` (the extension folder) and ``site_packages`` (what its wheels
    install into the site-packages that Blender shares between all extensions)."""
    with zipfile.ZipFile(zip_path) as zf:
        infos = zf.infolist()
        installed = 0
        for info in infos:
            if info.filename.endswith(".whl"):
                with zf.open(info) as fh, zipfile.ZipFile(fh) as whl:
                    installed += sum(i.file_size for i in whl.infolist())
        return {"zip": zip_path.stat().st_size, "unpacked": sum(i.file_size for i in infos),
                "site_packages": installed}


def _blender_ext(tool: Path, argv: list[str]) -> str:
    proc = subprocess.run([sys.executable, str(tool), *argv], capture_output=True, text=True)
    if proc.returncode != 0:
        raise Adv3dError(f"blender_ext {argv[0]} failed: {(proc.stdout + proc.stderr).strip()[-2000:]}")
    return proc.stdout


def _zip_dir(src: Path, target: Path) -> None:
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(src.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                zf.write(path, path.relative_to(src).as_posix())


# --------------------------------------------------------------------------- validation

REQUIRED_MANIFEST = {"schema_version": str, "id": str, "version": str, "name": str, "tagline": str,
                     "maintainer": str, "type": str, "blender_version_min": str, "license": list}


def check_manifest(manifest: dict, names: set[str], where: str) -> list[str]:
    """Problems with an extension manifest and the archive's file ``names`` (empty = valid)."""
    problems = []
    for key, typ in REQUIRED_MANIFEST.items():
        if not isinstance(manifest.get(key), typ):
            problems.append(f"{where}: {key}: expected a {typ.__name__}")
    if manifest.get("schema_version") != "1.0.0":
        problems.append(f"{where}: schema_version: expected \"1.0.0\"")
    if manifest.get("id") != EXTENSION_ID:
        problems.append(f"{where}: id: expected \"{EXTENSION_ID}\"")
    if manifest.get("type") != "add-on":
        problems.append(f"{where}: type: expected \"add-on\"")
    wheels = manifest.get("wheels", [])
    if not any(Path(w).name.startswith("adv3d-") for w in wheels):
        problems.append(f"{where}: wheels: the adv3d runner wheel is not listed")
    for w in wheels:
        arc = w[2:] if w.startswith("./") else w
        if arc not in names:
            problems.append(f"{where}: wheels: {w} is listed but not in the archive")
        if Path(w).name.split("-")[0].lower() in {"numpy", "torch", "bpy"}:
            problems.append(f"{where}: wheels: {w} must not be shipped (Blender provides numpy; no torch/bpy)")
    if "__init__.py" not in names:
        problems.append(f"{where}: __init__.py missing")
    licences = manifest.get("license")
    if not isinstance(licences, list) or not any(x in ADDON_LICENCES for x in licences):
        problems.append(f"{where}: license: expected one of {', '.join(ADDON_LICENCES)} (the extensions platform's "
                        "licence for add-ons)")
    if not isinstance(manifest.get("copyright"), list) or not manifest.get("copyright"):
        problems.append(f"{where}: copyright: expected a list such as [\"2026 name\"]")
    if "LICENSE" not in names:
        problems.append(f"{where}: LICENSE (the add-on's licence text) missing")
    if manifest.get("blender_version_max") != BLENDER_VERSION_MAX:
        problems.append(f"{where}: blender_version_max: expected \"{BLENDER_VERSION_MAX}\" (cp311 wheels: "
                        "Blender 5.1 and later run Python 3.13)")
    plats = manifest.get("platforms")
    binary = [Path(w).name for w in wheels if not Path(w).name.endswith("-none-any.whl")]
    if binary and (not isinstance(plats, list) or len(plats) != 1):
        problems.append(f"{where}: platforms: expected exactly the one platform the binary wheels are for")
    for w in binary:
        if "cp311" not in w:
            problems.append(f"{where}: wheels: {w} is not built for CPython 3.11")
        elif isinstance(plats, list) and len(plats) == 1 and not _wheel_platform_ok(w, plats[0]):
            problems.append(f"{where}: wheels: {w} does not load on {plats[0]}")
    for name in sorted(names):
        if name in DEV_ONLY or name.startswith(("tests/", "bench/")) or "__pycache__" in name:
            problems.append(f"{where}: {name}: a development file in the extension")
    return problems


def _wheel_platform_ok(wheel: str, platform: str) -> bool:
    plat = wheel[:-4].split("-")[-1]
    return platform in PLATFORM_TAGS and any(t in PLATFORM_TAGS[platform] or _compatible_tag(t, platform)
                                             for t in plat.split("."))


def validate_extension_zip(path: Path, bpy_check: bool = True) -> None:
    """Validate a built extension zip; raises ``Adv3dError`` listing every problem.

    Checks: Blender's own ``blender_ext validate`` (when bpy is installed), the manifest fields
    and listed wheels (ours), that the add-on source never imports torch, and (``bpy_check``)
    that the zip installs and registers in a bpy child process.
    """
    import tomllib

    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
            sources = {n: zf.read(n).decode() for n in names if n.endswith(".py") and "/" not in n}
    except (OSError, KeyError, zipfile.BadZipFile, tomllib.TOMLDecodeError) as exc:
        raise Adv3dError(f"{path}: not a valid extension archive ({exc})") from None
    problems = check_manifest(manifest, names, str(path))
    for name, src in sorted(sources.items()):
        if re.search(r"(?m)^\s*(import torch|from torch\b)", src):
            problems.append(f"{path}: {name} imports torch (the add-on must never import torch)")
    tool = blender_ext_script()
    if tool is not None:
        try:
            _blender_ext(tool, ["validate", str(path)])
        except Adv3dError as exc:
            problems.append(str(exc))
    if problems:
        raise Adv3dError("extension validation failed:\n  " + "\n  ".join(problems))
    if bpy_check and importlib.util.find_spec("bpy") is not None:
        _run_child([sys.executable, str(ADDON_DIR / "selfcheck.py"), str(path)], "install check", timeout=300)
