"""``adv3d assets ...``: curate the vehicle library (import, exclude, list, check, preview).

``assets/vehicles/build_library.sh`` is the exact sequence of these commands that made the
shipped library; rerunning it gives the same library.json and the same mesh bytes.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ConfigError, MeshImportError, UsageError
from ..vehicle_classes import VEHICLE_CLASSES


def _class_name(text: str) -> str:
    """``--class``: a lower-case class name (``vehicle_classes.is_class_name``)."""
    from ..vehicle_classes import is_class_name

    if not is_class_name(text):
        raise argparse.ArgumentTypeError(f"expected a lower-case class name such as sedan or suv (got {text!r})")
    return text


def _asset_id(text: str) -> str:
    """``--id``: an asset id (``library.ID_EXPECTED``)."""
    from .library import _ID_RE, ID_EXPECTED

    if not _ID_RE.match(text):
        raise argparse.ArgumentTypeError(f"expected {ID_EXPECTED} (got {text if len(text) <= 60 else text[:57] + '...'!r})")
    return text


def register(subparsers) -> None:
    from .. import argtypes as at

    parser = subparsers.add_parser("assets", help="curate the vehicle library (import, list, check)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="assets_command", metavar="ACTION")

    imp = sub.add_parser("import", help="convert mesh files into the library and record them")
    imp.add_argument("paths", nargs="+", metavar="PATH",
                     help=".glb .gltf .obj .ply .stl .fbx .blend, ApolloCar3D .json")
    imp.add_argument("--class", dest="vehicle_class", required=True, type=_class_name,
                     help="vehicle class: " + " ".join(VEHICLE_CLASSES[:8]) + " ... (any lower-case name)")
    imp.add_argument("--dimensions", nargs=3, type=at.number(0.0, 100.0, lo_open=True), metavar=("L", "W", "H"),
                     help="scale (anisotropically) to this real length, width, height in metres")
    imp.add_argument("--id", dest="asset_id", type=_asset_id, help="asset id (one PATH only); default PACK.file-stem")
    imp.add_argument("--up", type=at.axis, help="file axis that is up (+x -x +y -y +z -z); default from the format")
    imp.add_argument("--forward", type=at.axis, help="file axis the vehicle's front points to; default: longest horizontal axis")
    imp.add_argument("--convention", default="auto", choices=("auto", "none", "apollocar3d", "shapenet"),
                     help="dataset axis convention (auto: ApolloCar3D for .json, ShapeNet for "
                          "model_normalized.obj; none: the format's own axes)")
    imp.add_argument("--unit", default="auto", choices=("auto", "m", "cm", "mm", "in"),
                     help="file length unit (auto: guessed from the vehicle's length)")
    imp.add_argument("--library", type=Path, default=None, help="library.json (default assets/vehicles/library.json)")
    imp.add_argument("--exclude-from-shape-space", action="store_true",
                     help="keep the asset out of the PCA shape space (buses, trucks, ...)")
    imp.add_argument("--licence-file", type=Path, help="licence text to copy beside the meshes (default: found beside PATH)")
    imp.add_argument("--licence", dest="licence_name", help='licence name, e.g. "CC0-1.0" (default: read from the licence file)')
    imp.add_argument("--source-pack", help="pack folder name in the library (default: PATH's folder name)")
    imp.add_argument("--author", default="", help="author credited in the source record")
    imp.add_argument("--url", default="", help="where the pack comes from")
    imp.add_argument("--note", default="", help="why the asset was curated this way (recorded in curation.note)")
    imp.set_defaults(func=cmd_import)

    exc = sub.add_parser("exclude", help="record a source file deliberately left out of the library")
    exc.add_argument("paths", nargs="+", metavar="PATH")
    exc.add_argument("--reason", required=True)
    exc.add_argument("--source-pack", help="pack name (default: PATH's folder name)")
    exc.add_argument("--library", type=Path, default=None)
    exc.set_defaults(func=cmd_exclude)

    lst = sub.add_parser("list", help="print the library as a table")
    lst.add_argument("--library", type=Path, default=None)
    lst.add_argument("--markdown", action="store_true", help="print a Markdown table")
    lst.set_defaults(func=cmd_list)

    chk = sub.add_parser("check", help="validate library.json and that every mesh loads and matches it")
    chk.add_argument("--library", type=Path, default=None)
    chk.set_defaults(func=cmd_check)

    prv = sub.add_parser("preview", help="render top and side silhouettes of assets to PNG (check +x front, z=0)")
    prv.add_argument("ids", nargs="*", help="asset ids (default: all)")
    prv.add_argument("--library", type=Path, default=None)
    prv.add_argument("-o", "--output", type=Path, required=True, help="PNG file to write")
    prv.set_defaults(func=cmd_preview)

    parser.set_defaults(func=lambda args: (parser.print_help(), 2)[1])


def _library_path(arg: Path | None) -> Path:
    from .library import DEFAULT_LIBRARY

    return Path(arg) if arg is not None else DEFAULT_LIBRARY


def cmd_import(args) -> int:
    from ..progress import progress, status
    from ..vehicle_classes import plausibility_warning
    from .library import add_asset, load_or_new_library
    from .mesh_io import import_vehicle

    lib_path = _library_path(args.library)
    library = load_or_new_library(lib_path)
    paths = [Path(p) for p in args.paths]
    if args.asset_id and len(paths) != 1:
        raise UsageError("--id needs exactly one PATH")
    if args.up and args.forward and args.up[1:] == args.forward[1:]:
        raise UsageError(f"--up {args.up} and --forward {args.forward} must be different axes")
    dimensions = tuple(args.dimensions) if args.dimensions else None

    def read(path: Path):
        mesh, curation, report = import_vehicle(path, up=args.up, forward=args.forward, unit=args.unit,
                                                dimensions=dimensions, convention=args.convention)
        if dimensions:
            curation["scaled_to_dimensions"] = [float(v) for v in dimensions]
        return mesh, curation, report

    for path in progress(paths, desc="import", unit="file"):
        asset = add_asset(library, lib_path, path, args.vehicle_class, read, asset_id=args.asset_id,
                          pack=args.source_pack, licence_file=args.licence_file, licence_name=args.licence_name,
                          author=args.author, url=args.url, note=args.note,
                          in_shape_space=not args.exclude_from_shape_space)
        dims = asset.dimensions
        warning = plausibility_warning(asset.vehicle_class, dims)
        status(f"{asset.id}: {dims[0]:.2f} x {dims[1]:.2f} x {dims[2]:.2f} m, {asset.triangle_count} triangles"
               + (f"  WARNING: {warning}" if warning else ""))
    return 0


def cmd_exclude(args) -> int:
    from ..progress import status
    from .library import load_or_new_library, save_library, slug

    lib_path = _library_path(args.library)
    library = load_or_new_library(lib_path)
    for p in args.paths:
        path = Path(p)
        entry = {"pack": slug(args.source_pack or path.parent.name), "file": path.name, "reason": args.reason}
        library.excluded = [e for e in library.excluded
                            if (e["pack"], e["file"]) != (entry["pack"], entry["file"])] + [entry]
        status(f"excluded {entry['pack']}/{entry['file']}: {args.reason}")
    save_library(library, lib_path)
    return 0


def format_table(library, markdown: bool = False) -> str:
    """The library as a text (or Markdown) table: id, class, L/W/H, triangles, shape space."""
    header = ("id", "class", "L m", "W m", "H m", "tris", "shape space")
    rows = [(a.id, a.vehicle_class, f"{a.dimensions[0]:.2f}", f"{a.dimensions[1]:.2f}", f"{a.dimensions[2]:.2f}",
             str(a.triangle_count), "yes" if a.in_shape_space else "no") for a in library.assets]
    if markdown:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    return "\n".join(fmt.format(*r) for r in [header, *rows])


def cmd_list(args) -> int:
    from .library import load_library

    library = load_library(_library_path(args.library))
    print(format_table(library, markdown=args.markdown))
    n = len(library.shape_space_assets())
    print(f"{len(library.assets)} assets, {n} in the shape space, {len(library.excluded)} source files excluded")
    return 0


def check_library(library, tolerance: float = 1e-3) -> list[str]:
    """Every problem found in a loaded library (empty list: all good).

    Checks each mesh file loads, its triangle count and bounding box match the JSON (within
    ``tolerance`` metres), the origin convention (min z = 0, footprint centred) and that the
    licence file exists.
    """
    import numpy as np

    from ..errors import FileFormatError
    from ..fileio import resolve_inside
    from .mesh_io import read_library_mesh

    problems = []
    for asset in library.assets:
        try:
            mesh = read_library_mesh(library.path_of(asset))
        except (MeshImportError, FileFormatError) as exc:
            problems.append(f"{asset.id}: {exc}")
            continue
        lo, hi = mesh.bounds
        size = hi - lo
        if len(mesh.faces) != asset.triangle_count:
            problems.append(f"{asset.id}: {len(mesh.faces)} triangles, library.json says {asset.triangle_count}")
        if np.max(np.abs(size - np.asarray(asset.dimensions))) > tolerance:
            problems.append(f"{asset.id}: mesh size {np.round(size, 4).tolist()} != dimensions {list(asset.dimensions)}")
        if abs(lo[2]) > tolerance:
            problems.append(f"{asset.id}: lowest point at z = {lo[2]:.4f} m, expected 0 (on the ground)")
        centre = 0.5 * (lo[:2] + hi[:2])
        if np.max(np.abs(centre)) > tolerance:
            problems.append(f"{asset.id}: footprint centre at {np.round(centre, 4).tolist()}, expected the origin")
        try:  # inside the library folder, symlinks included
            licence = resolve_inside(library.root, asset.licence["file"], inside="the library folder")
        except FileFormatError as exc:
            problems.append(f"{asset.id}: licence file: {exc}")
            continue
        if not licence.is_file():
            problems.append(f"{asset.id}: licence file {asset.licence['file']} is missing")
    return problems


def cmd_check(args) -> int:
    from ..progress import status
    from .library import load_library

    path = _library_path(args.library)
    library = load_library(path)
    problems = check_library(library)
    for p in problems:
        print(f"PROBLEM {p}")
    if problems:
        print(f"{path}: {len(problems)} problem(s) in {len(library.assets)} assets")
        return 1
    status(f"{path}: OK, {len(library.assets)} assets load and match their records")
    return 0


def cmd_preview(args) -> int:
    from ..progress import status
    from .library import load_library
    from .library_preview import render_silhouettes

    library = load_library(_library_path(args.library))
    ids = args.ids or library.ids()
    render_silhouettes(library, ids, args.output)
    status(f"wrote {args.output}")
    return 0
