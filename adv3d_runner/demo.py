"""``adv3d demo``: the README's main job on the bundled defaults.

Loads the shipped vehicle library and shape space (building the shape space if it is missing),
decodes a vehicle from the centre of the latent box and one random sample, writes them as
meshes, then runs a short closed-loop Bayesian-optimisation attack with Autonomy-A on a bundled
highway scene and writes its report. The full protocol (budget 100, 5 s) is ``adv3d attack``.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .fileio import REPO_ROOT

DEMO_SCENE = REPO_ROOT / "scenes" / "highway" / "highway-benchmark-000000.json.gz"


def register(subparsers) -> None:
    from . import argtypes as at

    parser = subparsers.add_parser("demo", help="run the main job on the bundled defaults")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--seed", type=at.seed, default=0, help="seed of the random shape sample and the attack")
    parser.add_argument("--scene", type=Path, default=DEMO_SCENE, help=f"scene to attack (default {DEMO_SCENE})")
    parser.add_argument("--budget", type=at.integer(1, 1_000_000), default=16, help="attack queries (default 16; the paper uses 100)")
    parser.add_argument("--seconds", type=at.number(0.0, 3600.0, lo_open=True), default=3.0, help="episode length in seconds (default 3)")
    parser.add_argument("--no-attack", action="store_true", help="only decode the sample vehicles")
    parser.add_argument("--library", default=None,
                        help="vehicle library of the scene's actors (default: the bundled one; 'none': boxes)")
    parser.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from .progress import status
    from .shapes.library import load_library, resolve_library
    from .shapes.mesh_io import write_mesh
    from .shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace, build_shape_space

    library = resolve_library(getattr(args, "library", None))
    if library is not None:
        status(f"vehicle library: {len(library.assets)} assets, {len(library.shape_space_assets())} in the shape space")
    if DEFAULT_SHAPE_SPACE.exists():
        space = ShapeSpace.load(DEFAULT_SHAPE_SPACE)
    else:
        status(f"{DEFAULT_SHAPE_SPACE} is missing: building it (adv3d shapes build)")
        space = build_shape_space(load_library())  # the shipped space is the bundled library's
        space.save(DEFAULT_SHAPE_SPACE)
    status(f"shape space: K={space.k}, explained variance {np.round(space.explained_variance_ratio, 3).tolist()}")

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    samples = {"mean_vehicle": np.full(space.k + 2, 0.5), f"sample_seed{args.seed}": space.sample_unit(rng)}
    for name, u in samples.items():
        mesh = space.decode(u)
        path = args.out / f"{name}.glb"
        write_mesh(mesh, path)
        length, width, height = mesh.extents
        status(
            f"{path}: {len(mesh.faces)} triangles, {length:.2f} x {width:.2f} x {height:.2f} m, "
            f"watertight={mesh.is_watertight}, nearest library asset: {space.nearest_asset(u)}"
        )
    if not args.no_attack:
        run_demo_attack(args)
    return 0


def run_demo_attack(args: argparse.Namespace) -> None:
    """A short closed-loop BO attack (Autonomy-A) on one scene, then its markdown report."""
    from .attack.driver import AttackConfig, run_attack
    from .attack.report import write_report
    from .progress import status

    run_dir = args.out / "attack"
    config = AttackConfig(scenes=[str(args.scene)], algo="bo", budget=args.budget, mode="closed",
                          seconds=args.seconds, seed=args.seed, autonomy="A",
                          n_initial=min(11, max(2, args.budget // 3)), library=getattr(args, "library", None))
    status(f"attacking {args.scene.name}: BO, {args.budget} queries, {args.seconds:g} s closed-loop episodes "
           f"(a run that is stopped resumes from {run_dir}/queries.jsonl)")
    run_attack(config, run_dir, workers=1)
    report = write_report([run_dir])
    status(f"attack report: {report}")
