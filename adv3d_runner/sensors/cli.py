"""``adv3d lidar ...``: render one LiDAR frame of a scene to PLY points and a bird's-eye PNG."""
from __future__ import annotations

import argparse
from pathlib import Path


def _sensor(text: str) -> str:
    """``--sensor``: a LiDAR model name (``beams.get_model``)."""
    from ..errors import ConfigError
    from .beams import get_model

    try:
        get_model(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def register(subparsers) -> None:
    """Add ``lidar render`` and ``lidar models``."""
    from .. import argtypes as at

    parser = subparsers.add_parser("lidar", help="simulate the ego's LiDAR in a scene",
                                   description="Simulate the ego's LiDAR (Embree ray casting) in a scene.")
    sub = parser.add_subparsers(dest="lidar_command", metavar="SUBCOMMAND")
    parser.set_defaults(func=lambda args: parser.print_help() or 2)

    render = sub.add_parser("render", help="simulate one frame: points as PLY, optional bird's-eye PNG")
    render.add_argument("scene", help="scene file (.json or .json.gz)")
    render.add_argument("--frame", type=at.count, default=0, help="frame index (default 0)")
    render.add_argument("-o", "--output", required=True, help="output PLY (x, y, z, intensity, ring, label, sensor)")
    render.add_argument("--bev", help="also write a bird's-eye PNG here")
    render.add_argument("--sensor", type=_sensor, help="replace the rig's LiDAR model(s): hdl64, vlp32c, os1-128, generic-N")
    render.add_argument("--seed", type=at.seed, default=0, help="seed of range noise and ray drop (default 0)")
    render.add_argument("--ideal", action="store_true", help="no range noise, no ray drop")
    render.add_argument("--library", default=None,
                        help="vehicle library JSON for actor meshes (default: the bundled one if present; "
                             "'none' draws actors as boxes)")
    render.add_argument("--extent", type=at.number(0.0, 10000.0, lo_open=True), default=60.0, help="half-size of the bird's-eye view, m")
    render.set_defaults(func=_render)

    models = sub.add_parser("models", help="list the LiDAR models and their beam tables")
    models.set_defaults(func=_models)


def _load_library(arg: str | None):
    from ..errors import ConfigError
    from ..fileio import REPO_ROOT

    if arg is not None and arg.lower() == "none":
        return None
    path = Path(arg) if arg else REPO_ROOT / "assets" / "vehicles" / "library.json"
    if arg is None and not path.exists():
        return None
    try:
        from ..shapes.library import load_library
    except ModuleNotFoundError as exc:
        raise ConfigError(f"vehicle library support is not available: {exc}") from None
    return load_library(path)


def _render(args: argparse.Namespace) -> int:
    import numpy as np

    from ..errors import UsageError
    from ..progress import status
    from ..scene.schema import load_scene
    from .lidar import simulate_frame
    from .pointio import draw_bev, write_points_ply
    from .world import rig_from_scene, world_from_scene

    scene_path = Path(args.scene)
    scene = load_scene(scene_path)
    if not 0 <= args.frame < scene.frames:
        raise UsageError(f"--frame {args.frame}: scene {scene.id} has frames 0..{scene.frames - 1}")
    library = _load_library(args.library)
    world = world_from_scene(scene, library, scene_dir=scene_path.parent)
    overrides = {"range_noise": 0.0, "ray_drop": 0.0} if args.ideal else {}
    rig = rig_from_scene(scene, args.sensor, path=scene_path, **overrides)
    ego = scene.ego_poses()[args.frame]
    poses, valid = scene.all_actor_poses()
    actor_poses = poses[:, args.frame].copy()
    actor_poses[~valid[:, args.frame]] = np.nan
    frame = simulate_frame(world, rig, ego, actor_poses, np.random.default_rng(args.seed))
    meta = {
        "scene": scene.id, "frame": args.frame, "seed": args.seed,
        "ego_pose": [float(v) for v in ego],
        "sensors": [f"{s.model.name}@{','.join(f'{m:g}' for m in s.mount)}" for s in rig.sensors],
    }
    write_points_ply(args.output, frame, meta=meta)
    n_actor_pts = int((frame.label >= 0).sum())
    status(f"{args.output}: {len(frame)} points ({n_actor_pts} on {len(set(frame.label[frame.label >= 0]))} actors) "
           f"from {rig.n_rays} rays, {'library meshes' if library is not None else 'box actors'}")
    if args.bev:
        c, s = np.cos(ego[2]), np.sin(ego[2])
        boxes = []
        for i, actor in enumerate(scene.actors):
            if not valid[i, args.frame]:
                continue
            dx, dy = poses[i, args.frame, 0] - ego[0], poses[i, args.frame, 1] - ego[1]
            rel = np.array([c * dx + s * dy, -s * dx + c * dy, poses[i, args.frame, 2] - ego[2]])
            boxes.append((actor.id, rel, actor.dimensions))
        draw_bev(args.bev, frame, boxes=boxes, ego_dimensions=scene.ego.dimensions, extent=args.extent,
                 title=f"{scene.id} frame {args.frame}: {len(frame)} points, {n_actor_pts} on actors")
        status(f"{args.bev}: bird's-eye view")
    return 0


def _models(args: argparse.Namespace) -> int:
    import numpy as np

    from .beams import MODELS

    for name, model in MODELS.items():
        el = np.rad2deg(model.elevations)
        print(f"{name:8s} {model.beams:4d} beams [{el.min():+.2f}, {el.max():+.2f}] deg, {model.columns} columns, "
              f"{model.rays} rays, {model.max_range:g} m, sigma {model.range_noise:g} m, drop {model.ray_drop:g}")
        print(f"         {model.source}")
    return 0
