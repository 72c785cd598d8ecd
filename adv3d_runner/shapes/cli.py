"""``adv3d shapes build | decode | info | realism | realism-reference``: build, sample and inspect the
PCA shape space, and measure how realistic a shape is (docs/realism.md)."""
from __future__ import annotations

import argparse
from pathlib import Path


def _mesh_file(text: str) -> Path:
    """``-o``: a mesh file name whose suffix says its format (``mesh_io.MESH_SUFFIXES``)."""
    from .mesh_io import MESH_SUFFIXES

    if Path(text).suffix.lower() not in MESH_SUFFIXES:
        raise argparse.ArgumentTypeError(f"expected a file ending in one of {', '.join(MESH_SUFFIXES)} (got {text!r})")
    return Path(text)


def _unit_for(space, u):
    """``--u`` checked against the shape space's K + 2 (known once ``--space`` is loaded): a
    wrong length is a usage error."""
    from ..errors import ConfigError, UsageError

    try:
        return space.check_unit(u)
    except ConfigError as exc:
        raise UsageError(f"--u: {exc}") from None


def register(subparsers) -> None:
    from .. import argtypes as at
    from ..vehicle_classes import DIMENSION_RANGES
    from .names import METHODS

    p = subparsers.add_parser("shapes", help="build, decode and inspect the PCA vehicle shape space")
    sub = p.add_subparsers(dest="shapes_command", metavar="SUBCOMMAND")

    b = sub.add_parser("build", help="SDF volumes of the library's shape-space assets -> PCA shape space (.npz)")
    b.add_argument("--library", type=Path, default=None, help="library.json (default: the bundled library)")
    b.add_argument("--resolution", type=at.integer(8, 512), default=None, help="SDF grid resolution N (default 64)")
    b.add_argument("--k", type=at.integer(1, 64), default=None, help="number of principal components K (default 3)")
    b.add_argument("--method", default=None, choices=METHODS,
                   help="SDF inside/outside method: winding (default), winding-outward, floodfill, rayvote")
    b.add_argument("--truncation", type=at.number(0.0, 1.0, lo_open=True), default=None, help="SDF truncation in unit-cube units (default 0.1)")
    b.add_argument("--out", type=Path, default=None,
                   help="output .npz (default assets/shape_space/vehicles_<N>.npz)")
    b.set_defaults(func=_build)

    d = sub.add_parser("decode", help="decode a unit vector in [0,1]^(K+2) to a metric vehicle mesh")
    d.add_argument("--u", required=True, type=at.numbers(0.0, 1.0),
                   help="comma-separated unit vector: K latents then width and length scale, e.g. 0.5,0.5,0.5,0.5,0.5")
    d.add_argument("-o", "--out", type=_mesh_file, required=True, help="mesh file (.glb, .gltf, .obj, .ply or .stl)")
    d.add_argument("--space", type=Path, default=None, help="shape space .npz (default: the bundled one)")
    d.set_defaults(func=_decode)

    i = sub.add_parser("info", help="print a shape space's grid, components, latent bounds and assets")
    i.add_argument("--space", type=Path, default=None, help="shape space .npz (default: the bundled one)")
    i.set_defaults(func=_info)

    r = sub.add_parser("realism", help="realism figures of a shape: JSD, nearest vehicle, Mahalanobis, "
                                       "artefacts, dimensions (docs/realism.md)")
    what = r.add_mutually_exclusive_group(required=True)
    what.add_argument("--u", type=at.numbers(0.0, 1.0), help="comma-separated unit vector, as for decode")
    what.add_argument("--mesh", type=Path, help="any vehicle file the importer reads (.glb .gltf .obj .ply .stl "
                                                ".fbx .blend .json .ac .acc): SDF, decode and every check")
    what.add_argument("--set", nargs="+", type=Path, metavar="FILE",
                      help="vehicle files: set-level realism against the library (MMD, COV, 1-NNA with "
                           "Chamfer distance; Jensen-Shannon distance)")
    r.add_argument("--class", dest="vehicle_class", default=None, choices=list(DIMENSION_RANGES),
                   help="vehicle class for the dimension check (default: the nearest library model's)")
    r.add_argument("--space", type=Path, default=None, help="shape space .npz (default: the bundled one)")
    r.add_argument("--json", action="store_true", help="print the report as JSON")
    r.set_defaults(func=_realism)

    rr = sub.add_parser("realism-reference",
                        help="recompute the realism reference (BEV histogram of the CAD models, leave-one-out figures)")
    rr.add_argument("--library", type=Path, default=None, help="library.json (default: the bundled library)")
    rr.add_argument("--space", type=Path, default=None, help="shape space .npz (default: the bundled one)")
    rr.add_argument("--out", type=Path, default=None,
                    help="output .npz (default assets/shape_space/realism_reference.npz)")
    rr.set_defaults(func=_realism_reference)

    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _load_space(path: Path | None):
    from .shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace

    return ShapeSpace.load(path or DEFAULT_SHAPE_SPACE)


def _build(args: argparse.Namespace) -> int:
    import time

    from ..errors import ConfigError
    from ..fileio import REPO_ROOT
    from ..progress import is_quiet, status
    from .library import DEFAULT_LIBRARY, load_library
    from .sdf import DEFAULT_METHOD, DEFAULT_TRUNCATION, METHODS
    from .shape_space import DEFAULT_K, DEFAULT_RESOLUTION, build_shape_space

    res = args.resolution or DEFAULT_RESOLUTION
    k = args.k or DEFAULT_K
    method = args.method or DEFAULT_METHOD
    if method not in METHODS:
        raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    if not 8 <= res <= 512:
        raise ConfigError(f"--resolution must be in [8, 512], got {res}")
    if k < 1:
        raise ConfigError(f"--k must be >= 1, got {k}")
    out = args.out or (REPO_ROOT / "assets" / "shape_space" / f"vehicles_{res}.npz")
    library = load_library(args.library or DEFAULT_LIBRARY)
    t0 = time.perf_counter()
    space = build_shape_space(library, resolution=res, k=k, method=method,
                              truncation=args.truncation or DEFAULT_TRUNCATION, progress=not is_quiet())
    space.save(out)
    status(f"built shape space over {len(space.asset_ids)} assets at {res}^3 ({method}), K={space.k} "
           f"(rank {space.rank}) in {time.perf_counter() - t0:.1f} s -> {out}")
    status("explained variance ratio: " + ", ".join(f"{x:.3f}" for x in space.explained_variance_ratio))
    return 0


def _decode(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..progress import status
    from .mesh_io import MESH_SUFFIXES, write_mesh

    suffix = args.out.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ConfigError(f"-o must end in one of {', '.join(MESH_SUFFIXES)}, got {args.out.name!r}")
    u = args.u  # a list of numbers in [0, 1] (argtypes.numbers)
    import trimesh

    space = _load_space(args.space)
    _unit_for(space, u)
    info: dict = {}
    mesh = trimesh.Trimesh(*space.decode_arrays(u, info=info), process=False)
    write_mesh(mesh, args.out)
    z, scales = space.unit_to_latent(u)
    ext = mesh.extents
    dropped = ""
    if info["dropped_parts"] or info["dropped_cavities"]:
        dropped = (f"; dropped {info['dropped_parts']} small part(s) and {info['dropped_cavities']} cavity(ies), "
                   f"{info['dropped_volume_m3']:.3g} m^3")
    status(f"decoded z={[round(float(x), 4) for x in z]} width/length scale={[round(float(x), 3) for x in scales]}: "
           f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, {ext[0]:.2f} x {ext[1]:.2f} x {ext[2]:.2f} m, "
           f"{info['kept_parts']} part(s){dropped} (nearest library asset {space.nearest_asset(u)}) -> {args.out}")
    return 0


def _import_for_realism(path: Path):
    from .mesh_io import import_vehicle

    mesh, _curation, _report = import_vehicle(path)
    return mesh


def _realism_set(args: argparse.Namespace, space, ref) -> int:
    import json

    import numpy as np

    from .realism_set import meshes_set_realism

    meshes = []
    for path in args.set:
        m = _import_for_realism(path)
        meshes.append((np.asarray(m.vertices), np.asarray(m.faces)))
    rep = meshes_set_realism(meshes, ref)
    rep["reference"] = list(ref.asset_ids)
    if args.json:
        print(json.dumps(rep, indent=1))
        return 0
    print("\n".join([
        f"set          {rep['n_found']} shape(s) against {rep['n_reference']} library CAD models",
        f"MMD-CD       {rep['mmd_cd_m2']:.4f} m^2 (lower: every library model has a close found shape)",
        f"COV-CD       {rep['cov_cd'] * 100:.1f} % of the library models are some shape's nearest",
        f"1-NNA-CD     {rep['nna_cd'] * 100:.1f} % (50 %: indistinguishable from the library; 100 %: apart)",
        f"JS distance  {rep['jsd_distance']:.3f} (BEV histogram of the set against the library's; "
        f"sqrt of the divergence in nats, at most 0.833)",
    ]))
    return 0


def _realism(args: argparse.Namespace) -> int:
    import json
    import time

    from .realism import DIMENSION_RANGES, default_reference, mesh_realism_report, realism_report

    from ..errors import ConfigError

    if args.vehicle_class is not None and args.vehicle_class not in DIMENSION_RANGES:
        raise ConfigError(f"--class must be one of {', '.join(DIMENSION_RANGES)}, got {args.vehicle_class!r}")
    space = _load_space(args.space)
    ref = default_reference(space)
    if args.set:
        return _realism_set(args, space, ref)
    t0 = time.perf_counter()
    if args.mesh is not None:
        mesh = _import_for_realism(args.mesh)
        rep = mesh_realism_report(space, mesh.vertices, mesh.faces, ref, vehicle_class=args.vehicle_class)
        what = f"mesh {args.mesh.name}"
    else:
        u = args.u
        _unit_for(space, u)
        rep = realism_report(space, u, ref, vehicle_class=args.vehicle_class)
        what = f"shape        u={[round(x, 4) for x in u]}"
    dt = time.perf_counter() - t0
    if args.json:
        print(json.dumps(rep, indent=1))
        return 0
    lim = rep["limits"]
    flag = {k: ("  <- unrealistic" if k in rep["flags"] else "") for k in lim}
    dims = rep["dimensions_m"]
    body = rep["body_dimensions_m"]
    lines = [
        f"{what}  {dims[0]:.2f} x {dims[1]:.2f} x {dims[2]:.2f} m overall, body {body[0]:.2f} x {body[1]:.2f} x "
        f"{body[2]:.2f} m",
    ]
    if args.mesh is not None:
        src, drop, out = rep["source_dimensions_m"], rep["dropped_extent_m"], rep["outside_source_m"]
        lines.append(f"SDF          source {src[0]:.2f} x {src[1]:.2f} x {src[2]:.2f} m; decoding lost "
                     + "/".join(f"{x:.2f}" for x in drop) + " m of L/W/H; decoded surface at most "
                     f"{out[0]:.3f} m (99 %: {out[1]:.3f} m) from the source")
    lines += [
        f"JSD          {rep['jsd']:.3f} Jensen-Shannon distance (limit {lim['jsd']:.3f}){flag['jsd']}",
        f"nearest      {rep['nearest_asset']} at {rep['nearest_chamfer_m']:.3f} m Chamfer "
        f"(limit {lim['nearest_chamfer_m']:.3f}){flag['nearest_chamfer_m']}; "
        f"nearest latent {rep['nearest_latent_asset']} at {rep['nearest_latent_distance']:.3f}",
        f"Mahalanobis  {rep['mahalanobis']:.2f} (limit {lim['mahalanobis']:.2f}){flag['mahalanobis']}",
        f"parts        {rep['parts_before_cleanup']} before clean-up ({rep['floating_parts']} floating, "
        f"{rep['cavities']} cavities), {rep['parts_after_cleanup']} after; clean-up drops "
        f"{rep['dropped_volume_fraction'] * 100:.3f} % of the volume; floating "
        f"{rep['floating_volume_fraction'] * 100:.3f} % (limit {lim['floating_volume_fraction'] * 100:.3f} %)"
        f"{flag['floating_volume_fraction']}",
        f"genus        {rep['genus']} (robust {rep['genus_robust']}){flag['genus_robust']}",
        f"thinnest     {rep['thinnest_wall_m']:.3f} m wall, limit {lim['thinnest_wall_m']:.3f} m "
        f"({rep['thin_wall_fraction'] * 100:.1f} % of the surface thinner than a voxel){flag['thinnest_wall_m']}",
        f"dimensions   class {rep['dimension_class']}, body (no mirrors): excess L/W/H "
        + "/".join(f"{x * 100:.0f} %" for x in rep["dimension_excess"])
        + f"; plausible as {', '.join(rep['plausible_classes']) or 'no class'}{flag['dimension_excess']}",
        f"verdict      {'realistic' if rep['realistic'] else 'unrealistic: ' + ', '.join(rep['flags'])}"
        f"  ({dt * 1000:.0f} ms)",
    ]
    print("\n".join(lines))
    return 0


def _realism_reference(args: argparse.Namespace) -> int:
    import time

    from ..progress import is_quiet, status
    from .library import DEFAULT_LIBRARY, load_library
    from .realism import DEFAULT_REFERENCE, build_reference

    space = _load_space(args.space)
    library = load_library(args.library or DEFAULT_LIBRARY)
    t0 = time.perf_counter()
    ref = build_reference(library, space, progress=not is_quiet())
    out = ref.save(args.out or DEFAULT_REFERENCE)
    status(f"realism reference over {len(ref.asset_ids)} CAD models in {time.perf_counter() - t0:.1f} s -> {out}; "
           f"leave-one-out JSD {ref.jsd_loo.min():.3f}-{ref.jsd_loo.max():.3f}, "
           f"Chamfer max {ref.chamfer_limit_m:.3f} m, Mahalanobis max {ref.mahalanobis_limit:.2f}")
    return 0


def _info(args: argparse.Namespace) -> int:
    space = _load_space(args.space)
    g = space.grid
    lines = [
        f"shape space  {space.source}",
        f"grid         {g.resolution}^3, cube edge {g.extent_m:.3f} m (voxel {g.extent_m * g.voxel * 100:.1f} cm), "
        f"ground at z={g.ground_z:+.4f} (unit cube), truncation {g.truncation} ({g.truncation * g.extent_m:.3f} m)",
        f"method       {space.method}",
        f"K            {space.k} (rank {space.rank}); unit vector has {space.dim} entries "
        f"(K latents, width scale, length scale in {list(space.scale_range)})",
        "components   " + "  ".join(
            f"#{i}: var {v:.4g} ({r * 100:.1f}%) z in [{lo:+.4f}, {hi:+.4f}]"
            for i, (v, r, lo, hi) in enumerate(zip(space.explained_variance, space.explained_variance_ratio,
                                                    space.latent_min, space.latent_max))),
        f"assets ({len(space.asset_ids)}):",
    ]
    for aid, z in zip(space.asset_ids, space.latents):
        lines.append(f"  {aid:32s} z=" + " ".join(f"{x:+.4f}" for x in z))
    lines.append(f"content hash {space.content_hash}")
    print("\n".join(lines))
    return 0
