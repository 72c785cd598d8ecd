"""``adv3d scenes ...``: generate, import-commonroad, assign-assets, validate, info."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    from .. import argtypes as at

    p = subparsers.add_parser("scenes", help="generate, import, validate and inspect scene files")
    sub = p.add_subparsers(dest="scenes_command", metavar="SUBCOMMAND")

    g = sub.add_parser("generate", help="generate highway scenes with the IDM/MOBIL traffic model")
    g.add_argument("--out", required=True, help="output folder (one <id>.json.gz per scene)")
    g.add_argument("--count", type=at.positive_int, default=1, help="number of scenes (seeds SEED .. SEED+COUNT-1)")
    g.add_argument("--seed", type=at.seed, default=None,
                   help="first seed (default: the first seed of the split's reserved range)")
    g.add_argument("--split", default="benchmark", choices=("benchmark", "train"),
                   help="seed namespace: benchmark seeds [0, 100000), train seeds [100000, 1e9)")
    g.add_argument("--layout", default=None, choices=("straight", "curved", "onramp", "lanedrop"),
                   help="road layout (default: cycles through all by seed)")
    g.add_argument("--density", default=None, choices=("free", "light", "moderate", "dense", "congested"),
                   help="traffic density (default: cycles through all by seed)")
    g.add_argument("--profile", default="default", choices=("default", "us101"),
                   help="traffic and road parameters: default (the bundled benchmark's) or us101 (fitted to the "
                        "NGSIM US-101 training recordings; sets its own density)")
    g.add_argument("--library", default=None,
                   help="vehicle library whose assets the actors draw and record (default: the bundled one; "
                        "'none': record no asset)")
    g.set_defaults(func=_generate)

    a = sub.add_parser("assign-assets", help="record a library asset for every actor of scene files (in place)")
    a.add_argument("paths", nargs="+", help="scene files or folders")
    a.add_argument("--library", default=None, help="vehicle library (default: the bundled one)")
    a.add_argument("--rule", default="draw", choices=("draw", "nearest-size"),
                   help="draw: seeded by scene and actor id over every asset of the class (default); "
                        "nearest-size: the closest dimensions (the v1 rule)")
    a.add_argument("--overwrite", action="store_true", help="replace assets already recorded")
    a.set_defaults(func=_assign_assets)

    c = sub.add_parser("import-commonroad", help="convert a CommonRoad XML scenario into a scene")
    c.add_argument("file", help="CommonRoad scenario (.xml)")
    c.add_argument("--out", required=True, help="output scene file (.json or .json.gz)")
    c.add_argument("--seconds", type=at.number(0.0, 3600.0, lo_open=True), default=None, help="scene length in s (default: the recording)")
    c.add_argument("--extend", action="store_true",
                   help="extend a recording shorter than --seconds at constant speed (marked synthetic)")
    c.add_argument("--ego", type=at.count, default=None, help="obstacle id to use as ego (default: automatic rule)")
    c.add_argument("--ego-rank", type=at.count, default=0,
                   help="take the car ranked K by the automatic ego rule (0 = the first); gives variants of one "
                        "recording different egos")
    c.add_argument("--manifest", default=None,
                   help="export.json of `adv3d export`: its ego obstacle, and what CommonRoad has no field for "
                        "(heights, classes, library assets, the ego's wheelbase and LiDARs, the background)")
    c.set_defaults(func=_import_commonroad)

    v = sub.add_parser("validate", help="validate scene files (and their actors' asset ids against the library)")
    v.add_argument("paths", nargs="+", help="scene files or folders")
    v.add_argument("--library", default=None,
                   help="vehicle library JSON the asset ids must name (default: the bundled one; 'none': skip)")
    v.set_defaults(func=_validate)

    i = sub.add_parser("info", help="one line per scene: layout, lanes, actors, frames, vehicles ahead")
    i.add_argument("paths", nargs="+", help="scene files or folders")
    i.set_defaults(func=_info)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _scene_files(paths: list[str]) -> list[Path]:
    from .real import SPLIT_NAME

    out: list[Path] = []
    for item in paths:
        path = Path(item)
        if path.is_dir():  # a folder's split manifest (scenes/real/split.json) is not a scene
            out += sorted(q for q in path.rglob("*") if q.name.endswith((".json", ".json.gz")) and q.name != SPLIT_NAME)
        else:
            out.append(path)
    return out


def _generate(args: argparse.Namespace) -> int:
    from ..errors import ConfigError, UsageError
    from ..progress import status
    from .generate import SPLITS, check_split, generate_scenes

    if args.count < 1:
        raise ConfigError("--count must be >= 1")
    from ..shapes.library import resolve_library

    seed = SPLITS[args.split][1] if args.seed is None else args.seed
    for s in (seed, seed + args.count - 1):  # --seed, --count and --split that do not go together
        try:
            check_split(args.split, s)
        except ConfigError as exc:
            raise UsageError(f"--seed {seed} --count {args.count}: {exc}") from None
    library = resolve_library(args.library)
    paths = generate_scenes(args.out, args.count, seed, args.split, args.layout, args.density,
                            profile=args.profile, library=library)
    status(f"wrote {len(paths)} scene(s) to {args.out}")
    return 0


def _assign_assets(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..progress import status
    from ..shapes.library import resolve_library
    from .actors import assign_assets
    from .schema import load_scene, save_scene

    library = resolve_library(args.library)
    if library is None:
        raise ConfigError("assign-assets needs a vehicle library")
    files = _scene_files(args.paths)
    changed = 0
    for path in files:
        scene = load_scene(path)
        out = assign_assets(scene, library, overwrite=args.overwrite, rule=args.rule)
        if [a.asset for a in out.actors] != [a.asset for a in scene.actors]:
            save_scene(out, path)
            changed += 1
    status(f"{changed} of {len(files)} scene file(s) updated ({args.rule} over {len(library.assets)} assets)")
    return 0


def _import_commonroad(args: argparse.Namespace) -> int:
    from ..progress import status
    from .commonroad import import_commonroad
    from .schema import save_scene

    hints = None
    if args.manifest is not None:  # an adv3d export: its ego, and what CommonRoad cannot hold
        from .commonroad_export import apply_manifest, read_manifest

        hints = read_manifest(args.manifest)
    scene = import_commonroad(args.file, seconds=args.seconds, extend=args.extend,
                              ego_id=args.ego if hints is None or args.ego is not None else hints.ego_id,
                              ego_rank=args.ego_rank)
    if hints is not None:
        scene = apply_manifest(scene, hints, args.manifest)
    save_scene(scene, args.out)
    status(f"wrote {args.out}: {len(scene.lanes)} lanes, {len(scene.actors)} actors, {scene.frames} frames")
    return 0


def _validate(args: argparse.Namespace) -> int:
    from ..errors import FileFormatError
    from ..fileio import REPO_ROOT
    from .actors import check_assets
    from .schema import load_scene

    library = None
    if args.library is None or args.library.lower() != "none":
        from ..shapes.library import load_library

        path = Path(args.library) if args.library else REPO_ROOT / "assets" / "vehicles" / "library.json"
        library = load_library(path) if args.library or path.exists() else None
    bad = 0
    files = _scene_files(args.paths)
    for path in files:
        try:
            scene = load_scene(path)
            if library is not None:
                check_assets(scene, library, str(path))
        except FileFormatError as exc:
            bad += 1
            print(f"INVALID {exc}")
    print(f"{len(files) - bad} of {len(files)} scene file(s) valid")
    return 1 if bad else 0


def _info(args: argparse.Namespace) -> int:
    from .generate import vehicles_ahead
    from .schema import load_scene

    for path in _scene_files(args.paths):
        scene = load_scene(path)
        details = scene.source.details
        layout = details.get("layout", scene.source.kind)
        ahead = vehicles_ahead(scene)
        print(f"{scene.id}: layout={layout} density={details.get('density', '-')} lanes={details.get('lanes', '-')} map_lanes={len(scene.lanes)} "
              f"actors={len(scene.actors)} frames={scene.frames} ahead_50m_5s={len(ahead)}")
    return 0
