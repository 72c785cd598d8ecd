"""``adv3d export``: a found failure as a scenario other tools replay (docs/export.md).

Reads an attack run folder (run.json, summary.json, the best shape's closed-loop replay and
meshes of one scene and mode) and the scene file it attacked, and writes into a new folder:

    scenario.xml      CommonRoad 2020a: lanelets, every vehicle of the episode as a dynamic
                      obstacle (the attacked actors with the found shape's length and width; the
                      ego's driven closed-loop trajectory as obstacle ``ids.ego``), the planning
                      problem (the ego's initial state), dt 0.1 (``scene.commonroad_export``)
    scenario.xosc     OpenSCENARIO 1.2, and road.xodr (OpenDRIVE 1.5), through scenariogeneration
                      (``scene.openscenario``); the attacked actors' model3d is their glb
    shapes/actor<ID>.glb   the found shape of each attacked actor, as the attack wrote it (glTF,
                      y up, metres, origin at the footprint centre on the ground)
    library/          a vehicle library (docs/formats.md) with the found shapes and the assets of
                      the benign actors' meshes, so ``adv3d simulate --library`` draws the same world
    export.json       the manifest: source run, scene, mode, best query, cost, stack, the failure
                      (collision, at-fault, minimum distance, hardest braking), file list, ids,
                      the commands that replay it, and the ``scene`` hints the importer restores

Everything is read and checked before anything is written; the folder is written beside
``--out`` under a temporary name and renamed into place, so a failed export leaves nothing.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, FileFormatError, RunFailedError, UsageError
from ..sim.evaluate import hardest_braking  # noqa: F401  (the failure's hardest braking; tests use it from here)

#: hardest braking that counts as a failure (m/s^2; the avoidability rule, docs/attack.md)
HARD_BRAKING = -4.0
MANIFEST = "export.json"
FILES = {"commonroad": "scenario.xml", "openscenario": "scenario.xosc", "opendrive": "road.xodr",
         "library": "library/library.json"}
FOUND_PACK = "found"
#: what an export folder holds (``replay/``: where its manifest's replay commands write), so an
#: earlier export is replaced only when it holds nothing else
OWN_ENTRIES = (MANIFEST, "scenario.xml", "scenario.xosc", "road.xodr", "library", "shapes", "replay")


@dataclass(frozen=True)
class ExportResult:
    """The written folder and its manifest (the JSON document)."""

    out: Path
    manifest: dict


def _check_out(out: Path) -> None:
    """``--out`` is a new folder, an empty one or an earlier export (replaced); anything else is
    refused (UsageError, before anything is read or written)."""
    if out.exists() or out.is_symlink():
        if not out.is_dir() or out.is_symlink():
            raise UsageError(f"--out {out}: is a file, not a folder")
        entries = sorted(e.name for e in out.iterdir())
        if entries and not (out / MANIFEST).is_file():
            raise UsageError(f"--out {out}: the folder holds files that are not an adv3d export "
                             f"({', '.join(entries[:3])}; no {MANIFEST})")
        other = [e for e in entries if e not in OWN_ENTRIES]
        if other:
            raise UsageError(f"--out {out}: an earlier export, but it also holds {', '.join(other[:3])}; "
                             "give a new folder (replacing it would delete them)")
    blocker = next((p for p in out.parents if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise UsageError(f"--out {out}: {blocker} is a file, not a folder")


def _scene_path(run_dir: Path, ref: str, digest: str | None, scene_file: str | None):
    """The attacked scene, loaded and checked to be the one the run attacked (by content)."""
    from ..scene import load_scene
    from .evaluator import scene_digest_of

    if scene_file is not None:
        candidates = [Path(scene_file)]
    else:
        from ..fileio import REPO_ROOT

        candidates = [Path(ref), run_dir.parent / ref, run_dir / ref, REPO_ROOT / ref]
    path = next((p for p in candidates if p.is_file()), None)
    if path is None:
        where = scene_file or ref
        raise ConfigError(f"{run_dir}: the attacked scene file {where} is not found (from here, the run folder "
                          "or the repository); give it with --scene-file")
    scene = load_scene(path)
    if digest is not None and scene_digest_of(scene) != digest:
        raise ConfigError(f"{path}: not the scene run {run_dir} attacked (its content differs from run.json's "
                          "scene_sha256); give the attacked file with --scene-file")
    return path, scene


def _library(run: dict, run_dir: Path):
    """The run's vehicle library (None: boxes), checked against run.json's fingerprint."""
    from ..shapes.library import library_fingerprint, resolve_library
    from ..sim.episode import default_library

    arg = run.get("library")
    library = default_library() if arg is None else resolve_library(arg)
    want = run.get("library_fingerprint")
    if library is not None and want and library_fingerprint(library) != want:
        raise ConfigError(f"{run_dir}: the vehicle library {library.root / 'library.json'} is not the one the run "
                          "used (library_fingerprint differs from run.json's)")
    return library


def _speeds(poses: np.ndarray, logged: np.ndarray, dt: float) -> np.ndarray:
    """Per frame speed: the scene's logged speed where the pose is the log's (a replayed
    actor), else the distance to the neighbouring frames over time (a reacting one)."""
    out = np.asarray(logged, dtype=np.float64).copy()
    ok = np.isfinite(poses[:, 0])
    fd = np.zeros(len(poses))
    idx = np.flatnonzero(ok)
    if len(idx) > 1:
        xy = poses[idx, :2]
        fd[idx] = np.hypot(*np.gradient(xy, idx * dt, axis=0).T)
    bad = ~np.isfinite(out)
    out[bad] = fd[bad]
    return out


def export_run(run_dir: str | Path, scene_id: str, out: str | Path, *, mode: str | None = None,
               scene_file: str | None = None, command: str | None = None) -> ExportResult:
    """Export the best shape of ``scene_id`` (``mode``: closed or open; default the run's only
    mode, else closed) of the attack run ``run_dir`` into the folder ``out`` (module docstring).

    Raises:
        UsageError: a scene or mode the run does not have, ``out`` a file or a folder of other
            files.
        ConfigError / FileFormatError: not a run folder, a broken run file, no scene file.
        RunFailedError: the run has no best shape for that scene and mode (every query failed,
            the scene was skipped, or the run has not finished it).
    """
    from ..shapes.mesh_io import mesh_dimensions, read_library_mesh
    from ..sim.replay import actor_mesh_path, load_replay
    from .journal import read_run

    run_dir, out = Path(run_dir), Path(out)
    _check_out(out)
    try:
        from scenariogeneration import xosc  # noqa: F401  (checked before anything is written)
    except ImportError:
        raise ConfigError("OpenSCENARIO export needs scenariogeneration: pip install 'adv3d[export]'") from None
    run, _, summary = read_run(run_dir)
    ids = list(run.get("scene_ids") or [])
    scenes = summary.get("scenes", {})
    if scene_id not in ids and scene_id not in scenes:
        known = ", ".join(ids or list(scenes)) or "none"
        raise UsageError(f"--scene {scene_id}: run {run_dir} has no such scene (it has: {known})")
    entry = scenes.get(scene_id)
    if entry is None or entry.get("skipped") or not entry.get("modes"):
        why = (entry or {}).get("skipped") or "it has not finished that scene"
        raise RunFailedError(f"{run_dir}: no best shape of {scene_id} to export ({why})")
    modes = list(entry["modes"])
    if mode is None:
        mode = modes[0] if len(modes) == 1 else "closed"
    if mode not in entry["modes"]:
        raise UsageError(f"--mode {mode}: run {run_dir} has {scene_id} in mode(s) {', '.join(modes)}")
    best = entry["modes"][mode]
    files = best.get("files") or {}
    if best.get("best_index", -1) < 0 or best.get("best_unit") is None:
        raise RunFailedError(f"{run_dir}: no best shape of {scene_id} [{mode}] to export (every query failed)")
    if not files.get("replay") or not files.get("meshes") or not best.get("closed_loop_eval"):
        raise RunFailedError(f"{run_dir}: summary.json has no best-shape files for {scene_id} [{mode}] (the run "
                             "has not evaluated its best shape yet)")
    replay_path = run_dir / files["replay"]
    for rel in [files["replay"], *files["meshes"].values()]:
        if not (run_dir / rel).is_file():
            raise RunFailedError(f"{run_dir}: the best shape's file {rel} is missing (summary.json lists it)")
    replay = load_replay(replay_path, points=False)
    if replay.scene_id != scene_id:
        raise FileFormatError(replay_path, "$.scene.id", f"the scene {scene_id}", replay.scene_id)
    index = ids.index(scene_id) if scene_id in ids else None
    digests = run.get("scene_sha256") or []
    ref = entry.get("ref") or (run["scenes"][index] if index is not None else scene_id)
    scene_path, scene = _scene_path(run_dir, ref, digests[index] if index is not None and index < len(digests)
                                    else None, scene_file)
    library = _library(run, run_dir)
    metrics = best["closed_loop_eval"].get("metrics") or {}

    # ------------------------------------------------------------------ vehicles of the episode
    from ..scene.commonroad_export import Vehicle

    T, dt, start = replay.n_frames, float(replay.dt), int(replay.start_frame)
    targets = {int(t) for t in entry.get("targets", [])}
    meshes = {int(k): v for k, v in files["meshes"].items()}
    actor_ids = [a.id for a in replay.actors]
    ego_id = scene.source.details.get("ego_obstacle_id")
    if not isinstance(ego_id, int) or ego_id in actor_ids or ego_id < 0:
        ego_id = max(actor_ids, default=0) + 1
    by_id = {a.id: a for a in scene.actors}
    actors, hints, shapes = [], [], {}
    scene_assets = {}
    if library is not None:
        from ..scene.actors import assign_assets

        scene_assets = {a.id: a.asset for a in assign_assets(scene, library).actors}
    for i, ra in enumerate(replay.actors):
        poses = np.asarray(ra.poses, dtype=np.float64)
        if not np.isfinite(poses[:, 0]).any():
            continue
        logged = np.full(T, np.nan)
        if ra.id in by_id and not replay.reactive:
            s = scene.actor_speeds(ra.id)[start:start + T]
            logged[:len(s)] = s
        dims = tuple(float(d) for d in ra.dimensions)
        asset = scene_assets.get(ra.id)
        if ra.adversarial or ra.id in targets:
            mesh = actor_mesh_path(replay_path, replay, i) or (run_dir / meshes[ra.id] if ra.id in meshes else None)
            if mesh is None:
                raise RunFailedError(f"{run_dir}: no mesh of the attacked actor {ra.id} in {files['replay']}")
            shape = read_library_mesh(mesh)
            shapes[ra.id] = (mesh, shape, mesh_dimensions(shape))
            asset = f"{FOUND_PACK}.actor{ra.id}"
        actors.append(Vehicle(ra.id, ra.cls, dims, poses, _speeds(poses, logged, dt)))
        hints.append({"obstacle_id": ra.id, "class": ra.cls, "dimensions": list(dims),
                      "asset": asset if library is not None else None,
                      "adversarial": bool(ra.id in shapes)})
    if not shapes:
        raise RunFailedError(f"{run_dir}: the replay of {scene_id} [{mode}] has no attacked actor")
    ego = Vehicle(int(ego_id), "sedan", tuple(float(d) for d in replay.ego_dimensions),
                  np.asarray(replay.ego_poses, dtype=np.float64), np.asarray(replay.ego_speeds, dtype=np.float64),
                  initial_acceleration=float(scene.ego_accelerations()[start]))

    # ------------------------------------------------------------------ the failure
    collision = metrics.get("collision") or {}
    braking = hardest_braking(replay.ego_speeds, dt)
    failure = {
        "collision": bool(collision.get("collided", False)), "at_fault": bool(collision.get("at_fault", False)),
        "collision_frame": collision.get("first_frame", -1), "collision_actors": list(collision.get("actors", [])),
        "min_distance_m": metrics.get("min_distance"), "hardest_braking_mps2": round(braking, 4),
        "hard_braking": bool(braking < HARD_BRAKING), "hard_braking_threshold_mps2": HARD_BRAKING,
        "off_road": bool(metrics.get("off_road", False)), "progress_m": metrics.get("progress_m"),
    }
    original = (entry.get("original") or {}).get("metrics") or {}
    if original:
        failure["original"] = {"collision": bool((original.get("collision") or {}).get("collided", False)),
                               "min_distance_m": original.get("min_distance"),
                               "progress_m": original.get("progress_m")}
    versions = run.get("versions") or {}
    stack = dict(versions.get("stack") or {"name": run.get("autonomy")})
    seed = int(best.get("noise_seed", run.get("seed", 0)))
    seconds = round(T * dt, 6)

    digest = digests[index] if index is not None and index < len(digests) else None

    # ------------------------------------------------------------------ write (temporary folder)
    from ..fileio import make_parent

    made = make_parent(out)
    tmp = None
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp's 0700 -> a plain new folder's mode
        manifest = _write(tmp, run=run, run_dir=run_dir, scene=scene, scene_path=scene_path, scene_id=scene_id,
                          digest=digest, mode=mode, best=best, stack=stack, failure=failure, ego=ego,
                          actors=actors, hints=hints, shapes=shapes, library=library, dt=dt, seed=seed,
                          seconds=seconds, command=command, out=out)
        _swap_in(tmp, out)
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        for folder in made:  # deepest first: folders this export made, left empty
            try:
                folder.rmdir()
            except OSError:
                pass
        raise
    return ExportResult(out=out, manifest=manifest)


def _write(tmp: Path, *, run, run_dir, scene, scene_path, scene_id, digest, mode, best, stack, failure, ego,
           actors, hints, shapes, library, dt, seed, seconds, command, out) -> dict:
    """Write every file of the export into ``tmp``; returns the manifest."""
    from .. import __version__
    from ..fileio import write_json
    from ..scene.commonroad import import_commonroad
    from ..scene.commonroad_export import (MANIFEST_FORMAT, MANIFEST_VERSION, apply_manifest, read_manifest,
                                           write_commonroad)
    from ..scene.openscenario import entity_name, write_opendrive, write_openscenario

    source_text = (f"adv3d {__version__} export of attack run {run_dir.name}, scene {scene_id} [{mode}], "
                   f"query {best['best_index']}; scene source: {scene.source.kind}")
    ids = write_commonroad(tmp / FILES["commonroad"], scene.lanes, ego, actors, dt, name=scene_id,
                           author="adv3d export", affiliation="adv3d", source=source_text)
    # shapes and library
    (tmp / "shapes").mkdir()
    lib_files = _write_library(tmp / "library", library, shapes, hints, run_dir=run_dir, scene_id=scene_id,
                               mode=mode, best_index=best["best_index"])
    shape_docs = []
    for aid, (mesh_path, _, dims) in sorted(shapes.items()):
        name = f"shapes/actor{aid}.glb"
        shutil.copyfile(mesh_path, tmp / name)
        shape_docs.append({"actor": aid, "file": name, "dimensions_m": [round(float(d), 4) for d in dims],
                           "asset": f"{FOUND_PACK}.actor{aid}"})
    write_opendrive(tmp / FILES["opendrive"], scene.lanes, scene_id)
    write_openscenario(tmp / FILES["openscenario"], ego, actors, dt, name=scene_id, author="adv3d export",
                       description=source_text, wheelbase=float(scene.ego.wheelbase), road_file=FILES["opendrive"],
                       models={aid: f"shapes/actor{aid}.glb" for aid in shapes})
    bg = scene.background
    scene_hints = {
        "ego": {"obstacle_id": ego.obstacle_id, "dimensions": [float(d) for d in scene.ego.dimensions],
                "wheelbase": float(scene.ego.wheelbase),
                "sensors": [{"name": s.name, "model": s.model, "mount": [float(v) for v in s.mount]}
                            for s in scene.ego.sensors]},
        "actors": hints,
        "background": {"shoulder_left": bg.shoulder_left, "shoulder_right": bg.shoulder_right,
                       "ground_margin": bg.ground_margin, "lane_markings": bg.lane_markings,
                       "barriers": [{"kind": b.kind, "height": b.height, "polyline": np.asarray(b.polyline).tolist()}
                                    for b in bg.barriers], "meshes": []},
    }
    autonomy = str(run.get("autonomy"))
    sim = (f"adv3d simulate {out}/replay/scene.json.gz --autonomy {autonomy} --seconds {seconds:g} --seed {seed}"
           + (" --reactive" if run.get("reactive") else "")
           + (f" --library {out}/{FILES['library']}" if library is not None else " --library none")
           + f" --out {out}/replay")
    notes = []
    if ids.gaps_filled:
        notes.append(f"actors {ids.gaps_filled} are absent for some frames between present ones; CommonRoad "
                     "trajectories have no gaps, so they are interpolated across them")
    if library is None:
        notes.append("the run drew every vehicle as a box (--library none), so the replay does too: the found "
                     "shape becomes a box of its dimensions; its mesh is in shapes/ and library/")
    if scene.background.meshes:
        notes.append("the scene's static background meshes are not exported")
    manifest = {
        "format": MANIFEST_FORMAT, "version": MANIFEST_VERSION,
        "source": {"run": str(run_dir), "scene": scene_id, "scene_file": str(scene_path),
                   "scene_sha256": digest,
                   "mode": mode, "best_index": int(best["best_index"]), "cost": best.get("best_cost"),
                   "autonomy": autonomy, "reactive": bool(run.get("reactive", False)), "seed": seed,
                   "start_frame": 0, "frames": len(ego.poses), "dt": dt, "adv3d": __version__,
                   "command": command},
        "stack": stack,
        "failure": failure,
        "files": {**FILES, "shapes": shape_docs},
        "ids": {"ego": ego.obstacle_id, "openscenario_ego": entity_name(None),
                "lanelets": {str(k): v for k, v in ids.lanelets.items()},
                "planning_problem": ids.planning_problem},
        "reproduce": [f"adv3d scenes import-commonroad {out}/{FILES['commonroad']} --manifest {out}/{MANIFEST} "
                      f"--out {out}/replay/scene.json.gz", sim],
        "licence": {"scene": scene.source.licence, "attribution": scene.source.attribution,
                    "shapes": lib_files.get("found_licence")},
        "notes": notes,
        "scene": scene_hints,
    }
    write_json(tmp / MANIFEST, manifest)
    # the CommonRoad file must come back as the episode: re-import it with the manifest now
    hints_read = read_manifest(tmp / MANIFEST)
    back = apply_manifest(import_commonroad(tmp / FILES["commonroad"], ego_id=hints_read.ego_id), hints_read,
                          tmp / MANIFEST)
    if back.frames != len(ego.poses) or np.abs(back.ego_poses()[:, :2] - ego.poses[:, :2]).max() > 0.02:
        raise ConfigError(f"{scene_id}: the written CommonRoad file does not read back as the episode")
    return manifest


def _write_library(root: Path, library, shapes: dict, hints: list[dict], *, run_dir: Path, scene_id: str, mode: str,
                   best_index: int) -> dict:
    """A vehicle library at ``root``: the found shapes (pack ``found``) and the run library's
    assets the benign actors use (mesh and licence files copied)."""
    from ..shapes.library import VehicleAsset, VehicleLibrary, save_library

    root.mkdir()
    lib = VehicleLibrary(root=root)
    used = {h["asset"] for h in hints if h["asset"] and not h["adversarial"]}
    if library is not None:
        for asset in library.assets:
            if asset.id not in used:
                continue
            for rel in (asset.file, asset.licence.get("file")):
                if rel and not (root / rel).exists():
                    (root / rel).parent.mkdir(parents=True, exist_ok=True)
                    src = library.root / rel
                    if src.is_file():
                        shutil.copyfile(src, root / rel)
            lib.put(asset)
    shape_licences = sorted({a.licence.get("name", "?") for a in (library.assets if library else [])
                             if a.in_shape_space})
    found_licence = {"name": shape_licences[0] if len(shape_licences) == 1 else "LicenseRef-shape-space",
                     "file": f"{FOUND_PACK}/LICENSE.txt"}
    (root / FOUND_PACK).mkdir()
    (root / FOUND_PACK / "LICENSE.txt").write_text(
        "Shapes found by an adv3d attack, decoded from the adv3d shape space, which is built over the\n"
        "vehicle library's shape-space assets. Their licences apply to these derived shapes: "
        f"{', '.join(shape_licences) or 'unknown'}\n(see README.md, Licences, of adv3d for the packs and authors).\n")
    for aid, (mesh_path, mesh, dims) in sorted(shapes.items()):
        file = f"{FOUND_PACK}/actor{aid}.glb"
        shutil.copyfile(mesh_path, root / file)
        cls = next(h["class"] for h in hints if h["obstacle_id"] == aid)
        lib.put(VehicleAsset(
            id=f"{FOUND_PACK}.actor{aid}", file=file, vehicle_class=cls,
            dimensions=tuple(round(float(d), 4) for d in dims), in_shape_space=False,
            triangle_count=max(1, int(len(mesh.faces))),
            source={"pack": FOUND_PACK, "file": Path(mesh_path).name, "run": str(run_dir), "scene": scene_id,
                    "mode": mode, "query": int(best_index)},
            licence=found_licence,
            curation={"note": "best shape of an adv3d attack, stored as the attack wrote it (glTF, y up)"},
            cleaning={}))
    save_library(lib, root / "library.json")
    return {"found_licence": found_licence}


def _swap_in(tmp: Path, out: Path) -> None:
    """Put the finished folder ``tmp`` at ``out`` (an earlier export there is replaced)."""
    if out.exists():
        old = out.parent / f".{out.name}.old"
        shutil.rmtree(old, ignore_errors=True)
        out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(out)


def manifest_summary(manifest: dict[str, Any]) -> str:
    """One line: what was exported and the failure."""
    f, s = manifest["failure"], manifest["source"]
    parts = [f"collision{' (at fault)' if f['at_fault'] else ''}" if f["collision"] else "no collision",
             f"min distance {f['min_distance_m']:.2f} m" if f["min_distance_m"] is not None else "min distance n/a",
             f"hardest braking {f['hardest_braking_mps2']:.2f} m/s^2" + (" (hard)" if f["hard_braking"] else "")]
    return f"{s['scene']} [{s['mode']}] query {s['best_index']} (cost {s['cost']:.4g}): " + ", ".join(parts)
