"""``adv3d simulate``: run one episode and write its metrics and replay.

    adv3d simulate SCENE [--open-loop] [--seconds 5] [--reactive] [--autonomy A|B|oracle|A-lanefollow]
                   [--points] [--seed S] [--start-frame F] [--library PATH|none] --out DIR

Writes ``DIR/metrics.json`` (format "adv3d-episode-metrics") and ``DIR/replay.json.gz``
(format "adv3d-replay", plus ``DIR/replay.points.npz`` with ``--points``), and prints a
one-line summary.
"""
from __future__ import annotations

from pathlib import Path


def register(subparsers) -> None:
    from .. import argtypes as at
    from ..autonomy.names import stack_spec

    p = subparsers.add_parser("simulate", help="run one closed- or open-loop episode on a scene",
                              description=__doc__.splitlines()[0])
    p.add_argument("scene", help="scene file (.json or .json.gz)")
    p.add_argument("--open-loop", action="store_true", help="the ego replays its log instead of following its plans")
    p.add_argument("--seconds", type=at.number(0.0, 3600.0, lo_open=True), default=5.0, help="episode length in s (default 5)")
    p.add_argument("--reactive", action="store_true", help="actors react to the ego (IDM/MOBIL) instead of replaying")
    p.add_argument("--autonomy", type=stack_spec, default="A", metavar="STACK",
                   help="any stack of `adv3d stacks list`, package.module:factory, exec:COMMAND, tcp://HOST:PORT "
                        "or unix:PATH (docs/stacks.md); A: learned detector + predictor (needs the shipped weights); B: instance-free, the learned "
                        "implicit occupancy-and-flow model + the same planner; oracle: ground-truth "
                        "boxes of the actors the LiDAR hits + lane-following prediction; A-lanefollow: learned detector + lane-following prediction; A-fast: A with the 0.4 m detector (default A)")
    p.add_argument("--points", action="store_true", help="store the LiDAR points in the replay (large)")
    p.add_argument("--seed", type=at.seed, default=0, help="seed of the LiDAR noise (default 0)")
    p.add_argument("--start-frame", type=at.count, default=0, help="first scene frame (default 0)")
    p.add_argument("--library", default=None, help="vehicle library JSON (default: the bundled one); 'none' = boxes")
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_simulate)


def _simulate(args) -> int:
    from ..autonomy.stacks import make_stack
    from ..errors import ConfigError
    from ..fileio import write_json
    from ..progress import is_quiet, status
    from ..scene import load_scene
    from ..sensors.world import world_from_scene
    from .episode import default_library, run_episode
    from .evaluate import episode_metrics
    from .replay import replay_from_episode, save_replay

    if args.seconds <= 0:
        raise ConfigError(f"--seconds must be positive, got {args.seconds}")
    scene_path = Path(args.scene)
    scene = load_scene(scene_path)
    if args.start_frame >= scene.frames:
        from ..errors import UsageError

        raise UsageError(f"--start-frame {args.start_frame}: scene {scene.id} has frames 0..{scene.frames - 1}")
    stack = make_stack(args.autonomy)
    if args.library is None:
        library = default_library()
    elif args.library.lower() == "none":
        library = None
    else:
        from ..shapes.library import load_library

        library = load_library(args.library)
    world = world_from_scene(scene, library, scene_dir=scene_path.parent)
    result = run_episode(scene, stack, seconds=args.seconds, closed_loop=not args.open_loop, reactive=args.reactive,
                         world=world, seed=args.seed, start_frame=args.start_frame, record_points=args.points,
                         progress=not is_quiet())
    metrics = episode_metrics(result, scene.lanes)
    metrics["autonomy"] = args.autonomy
    metrics["stack"] = stack.stack_info.as_dict()  # name, version, fingerprint (docs/stacks.md)
    metrics["command"] = "adv3d simulate " + " ".join(_argv(args))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "metrics.json", metrics)
    replay = replay_from_episode(result, autonomy=args.autonomy, scene_file=str(scene_path),
                                 metadata={"command": metrics["command"], "stack": metrics["stack"]})
    save_replay(replay, out / "replay.json.gz")
    d, p, c = metrics["detection"], metrics["prediction"], metrics["collision"]

    def f(x, fmt="{:.3f}"):
        return "n/a" if x is None else fmt.format(x)

    if "occupancy" in metrics:  # instance-free: occupancy and flow instead of boxes and trajectories
        o = metrics["occupancy"]
        perception = (f"occupancy mAP {f(o['map'])} Soft-IoU {f(o['soft_iou'])} | flow-grounded mAP "
                      f"{f(o['flow_grounded_map'])} Soft-IoU {f(o['flow_grounded_soft_iou'])} | EPE {f(o['epe'], '{:.2f}')} m/s")
    else:
        d, p = d or {}, p or {}  # None: the stack does not provide them (not available)
        perception = (f"AP {f(d.get('ap'), '{:.3f}')} recall {f(d.get('recall'))} | "
                      f"minADE {f(p.get('min_ade'), '{:.2f}')} meanADE {f(p.get('mean_ade'), '{:.2f}')}")
    status(f"{scene.id}: {'open' if args.open_loop else 'closed'} loop{' reactive' if args.reactive else ''}, "
           f"{result.frames} frames | {perception} | "
           f"plan lat {metrics['planning_comfort']['lat']:.3f} jerk {metrics['planning_comfort']['jerk']:.3f} | "
           f"drive lat {metrics['driving_comfort']['lat']:.3f} jerk {metrics['driving_comfort']['jerk']:.3f} | "
           f"collision {'yes' if c['collided'] else 'no'} off-road {'yes' if metrics['off_road'] else 'no'} | "
           f"{f(metrics['fps'], '{:.1f}')} frames/s -> {out}")
    close = getattr(stack, "close", None)
    if close is not None:  # a stack in its own process ends with the command
        close()
    return 0


def _argv(args) -> list[str]:
    parts = [str(args.scene)]
    if args.open_loop:
        parts.append("--open-loop")
    parts += ["--seconds", f"{args.seconds:g}"]
    if args.reactive:
        parts.append("--reactive")
    parts += ["--autonomy", args.autonomy, "--seed", str(args.seed)]
    if args.start_frame:
        parts += ["--start-frame", str(args.start_frame)]
    if args.points:
        parts.append("--points")
    if args.library:
        parts += ["--library", args.library]
    parts += ["--out", str(args.out)]
    return parts
