"""The add-on's only door into ``adv3d_runner`` (numpy-only parts: shapes and scene).

Imports are done lazily, inside functions, so registering the add-on stays instant and a
missing optional piece only disables the operator that needs it. Nothing here imports bpy or
torch; this module can be unit-tested without Blender.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from adv3d_runner.errors import Adv3dError, FileFormatError

__all__ = ["Adv3dError", "FileFormatError", "load_space", "clear_space_cache", "realism_reference", "live_realism",
           "full_realism"]

# Loaded shape spaces keyed by absolute path; the file's mtime and size invalidate an entry, so
# a rebuild on disk is picked up without restarting Blender.
_SPACES: dict[str, tuple[tuple[float, int], Any]] = {}


def load_space(path: str | os.PathLike) -> Any:
    """The ``ShapeSpace`` stored at ``path`` (cached while the file is unchanged)."""
    from adv3d_runner.shapes.shape_space import ShapeSpace

    p = Path(path).expanduser().resolve()
    try:
        st = p.stat()
    except OSError:
        raise FileFormatError(p, "$", "an existing shape-space .npz file", "file not found") from None
    stamp = (st.st_mtime, st.st_size)
    hit = _SPACES.get(str(p))
    if hit is not None and hit[0] == stamp:
        return hit[1]
    space = ShapeSpace.load(p)
    _SPACES[str(p)] = (stamp, space)
    return space


def clear_space_cache() -> None:
    _SPACES.clear()


def unit_vector(latent: np.ndarray | list[float], k: int, width_scale: float, length_scale: float) -> np.ndarray:
    """The shape space's unit input ``[z_1..z_K, width, length]`` in [0, 1]^(K+2)."""
    u = np.empty(k + 2, dtype=np.float64)
    u[:k] = np.asarray(latent, dtype=np.float64)[:k]
    u[k] = width_scale
    u[k + 1] = length_scale
    return np.clip(u, 0.0, 1.0)


def save_space(space, path: str | os.PathLike) -> Path:
    """Write a shape space atomically and drop any cached copy of that path."""
    out = space.save(Path(path))
    _SPACES.pop(str(Path(path).expanduser().resolve()), None)
    return out


# Realism references keyed by shape-space content hash (docs/realism.md): the shipped file for
# the shipped space, else built once from the panel's library (the space's CAD models).
_REFERENCES: dict[str, Any] = {}


def realism_reference(space, library_path: str | os.PathLike | None = None) -> Any:
    """The realism reference of ``space``: the shipped one when it matches, else built from the
    library file ``library_path`` (a few seconds, once per space).

    Raises:
        Adv3dError: no reference for this space and no library that holds its assets.
    """
    from adv3d_runner.shapes import realism

    key = space.content_hash
    if key in _REFERENCES:
        return _REFERENCES[key]
    try:
        ref = realism.default_reference(space)
    except Adv3dError:
        if not library_path:
            raise
        from adv3d_runner.shapes.library import load_library

        try:
            ref = realism.build_reference(load_library(Path(library_path)), space)
        except KeyError as exc:
            raise Adv3dError(f"no realism reference: the library lacks the shape space's asset {exc}") from None
    _REFERENCES[key] = ref
    return ref


def _flag(ok: bool) -> str:
    return "ok" if ok else "OUT"


def live_realism(space, u: np.ndarray, vertices: np.ndarray, faces: np.ndarray, vehicle_class: str | None = None,
                 library_path: str | os.PathLike | None = None) -> list[str]:
    """The realism lines the Shape space panel shows while a slider moves: the cheap measures
    without the nearest-CAD-model search (``quick_measures(chamfer=False)``: JSD, Mahalanobis,
    dimensions against the class; ~2 ms, docs/realism.md "Per query and live")."""
    from adv3d_runner.shapes import realism

    ref = realism_reference(space, library_path)
    z, _ = space.unit_to_latent(u)
    q = realism.quick_measures(vertices, faces, ref, latent=z, latents=space.latents, vehicle_class=vehicle_class,
                               chamfer=False)
    dims = " x ".join(f"{x:.2f}" for x in q["dimensions_m"])
    lines = [f"JSD {q['jsd']:.3f} (library <= {ref.jsd_limit:.3f}) {_flag('jsd' not in q['flags'])}",
             f"Mahalanobis {q['mahalanobis']:.2f} (library <= {ref.mahalanobis_limit:.2f}) "
             f"{_flag('mahalanobis' not in q['flags'])}"]
    if q["dimension_excess"] is not None:
        worst = 100 * max(q["dimension_excess"])
        lines.append(f"{dims} m vs real {q['dimension_class']}: {'ok' if worst == 0 else f'+{worst:.0f} % OUT'}")
    plausible = realism.plausible_classes(q["dimensions_m"])
    lines.append("Real classes of this size: " + (", ".join(plausible) if plausible else "none"))
    return lines


def full_realism(space, u: np.ndarray, vehicle_class: str | None = None,
                 library_path: str | os.PathLike | None = None) -> tuple[dict, list[str]]:
    """The whole realism report of the slider shape (``realism.realism_report``; 0.1-0.3 s in
    Blender) and the lines the panel shows for it."""
    from adv3d_runner.shapes import realism

    ref = realism_reference(space, library_path)
    rep = realism.realism_report(space, u, ref, vehicle_class=vehicle_class)
    lines = [f"JSD {rep['jsd']:.3f}, nearest {rep['nearest_asset']} ({rep['nearest_chamfer_m']:.3f} m)",
             f"Mahalanobis {rep['mahalanobis']:.2f}; parts {rep['parts_before_cleanup']} "
             f"(dropped {100 * rep['dropped_volume_fraction']:.2f} % vol.)",
             f"Genus {rep['genus']}/{rep['genus_robust']} (raw/robust); thinnest wall {rep['thinnest_wall_m']:.2f} m",
             "Realistic" if rep["realistic"] else "Fails: " + ", ".join(rep["flags"])]
    return rep, lines


# -- the stacks the runner can attack (docs/stacks.md) -----------------------------------------

#: Shown when the runner cannot be asked (not found, or it failed): adv3d's own stacks.
FALLBACK_STACKS = (("A", "Autonomy-A", "The shipped detector and predictor (torch, in the runner)"),
                   ("A-fast", "Autonomy-A, fast detector", "Autonomy-A with the 0.4 m detector"),
                   ("B", "Autonomy-B", "Instance-free: the learned occupancy-and-flow model"),
                   ("oracle", "Oracle", "Ground-truth perception (fast)"))
_STACKS: dict[tuple[str, ...], tuple[tuple[str, str, str], ...]] = {}


def runner_stacks(command: list[str], timeout: float = 60.0) -> tuple[tuple[str, str, str], ...]:
    """(name, label, description) of every stack the runner ``command`` lists
    (``adv3d stacks list --json``: its own and the registered plugins), asked once per command;
    :data:`FALLBACK_STACKS` when it cannot be asked. A plugin that cannot be built is left out."""
    import json
    import subprocess

    key = tuple(command)
    if key not in _STACKS:
        items = None
        if command:
            try:
                out = subprocess.run([*command, "stacks", "list", "--json"], capture_output=True, text=True,
                                     timeout=timeout)
                rows = json.loads(out.stdout) if out.returncode == 0 else None
                items = tuple((r["name"], r["name"], f"{r.get('version', '')}; provides "
                               f"{', '.join(r.get('provides', [])) or 'a plan only'} ({r['source']})")
                              for r in rows if "error" not in r) if rows else None
            except (OSError, subprocess.SubprocessError, ValueError, KeyError, TypeError):
                items = None
        _STACKS[key] = items or FALLBACK_STACKS
    return _STACKS[key]
