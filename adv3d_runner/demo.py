"""``adv3d demo``: the README's main job on the bundled defaults.

Loads the shipped vehicle library and shape space (building the shape space if it is missing),
decodes a vehicle from the centre of the latent box and one random sample, and writes them as
meshes. Later issues extend it to a short attack on a bundled scene.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def register(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="run the main job on the bundled defaults")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default out/demo)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random shape sample")
    parser.set_defaults(func=run_demo)


def run_demo(args: argparse.Namespace) -> int:
    from .progress import status
    from .shapes.library import load_library
    from .shapes.mesh_io import write_mesh
    from .shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace, build_shape_space

    library = load_library()
    status(f"vehicle library: {len(library.assets)} assets, {len(library.shape_space_assets())} in the shape space")
    if DEFAULT_SHAPE_SPACE.exists():
        space = ShapeSpace.load(DEFAULT_SHAPE_SPACE)
    else:
        status(f"{DEFAULT_SHAPE_SPACE} is missing: building it (adv3d shapes build)")
        space = build_shape_space(library)
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
    return 0
