"""``adv3d export RUN --scene S [--mode closed|open] --out DIR``: a found failure as CommonRoad,
OpenSCENARIO and glb files another tool replays (``attack/export.py``, docs/export.md)."""
from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write a found failure as a CommonRoad / OpenSCENARIO scenario with its shape (glb)",
        description="Write the best shape of scene S of an attack run as a scenario another tool replays: "
                    "CommonRoad XML (scenario.xml), OpenSCENARIO + OpenDRIVE (scenario.xosc, road.xodr), the shape "
                    "(shapes/actor<ID>.glb), a vehicle library of the episode's meshes and a manifest "
                    "(export.json: source, stack, the failure, how to replay it). See docs/export.md.")
    p.add_argument("run", help="attack run folder (runs/NAME)")
    p.add_argument("--scene", required=True, help="scene id of the run (summary.json's scenes)")
    p.add_argument("--mode", choices=("closed", "open"), default=None,
                   help="which search's best shape (default: the run's only mode, else closed); the exported "
                        "episode is the best shape's closed-loop evaluation either way")
    p.add_argument("--scene-file", default=None,
                   help="the attacked scene file, when its path in the run is not found from here (checked by "
                        "content against run.json)")
    p.add_argument("--out", required=True, help="output folder: new, empty, or an earlier export (replaced)")
    p.set_defaults(func=_export)


def _export(args) -> int:
    from ..progress import status
    from .export import export_run, manifest_summary

    command = "adv3d export " + " ".join(
        [args.run, "--scene", args.scene] + (["--mode", args.mode] if args.mode else [])
        + (["--scene-file", args.scene_file] if args.scene_file else []) + ["--out", args.out])
    result = export_run(args.run, args.scene, args.out, mode=args.mode, scene_file=args.scene_file, command=command)
    status(f"{manifest_summary(result.manifest)} -> {result.out}")
    return 0
