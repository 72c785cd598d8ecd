# SPDX-License-Identifier: GPL-3.0-or-later
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
_PATHS: dict[int, tuple[Any, Path]] = {}  # id(space) -> (space, the file it was loaded from)


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
    _PATHS[id(space)] = (space, p)
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


# Realism references (docs/realism.md) keyed by shape-space content hash. A space with a known
# reference (the shipped file for the shipped space, else the runner's content-keyed cache,
# ``realism.known_reference``) has it at once; for any other the reference is built from the
# library in a background thread (seconds to minutes: it samples every CAD model) and cached on
# disk by content, so no slider move ever waits for it.
_REFERENCES: dict[str, Any] = {}
_BUILDS: dict[str, Any] = {}   # content hash -> the thread building its reference
_FAILED: dict[tuple, str] = {}  # (content hash, library path) -> why no reference could be built
_KEYS: dict[int, tuple[Any, str]] = {}  # id(space) -> (space, content hash): hashing costs ~10 ms


class ReferencePending(Adv3dError):
    """The realism reference of this shape space is being built in the background."""


def space_key(space) -> str:
    """``space.content_hash``, computed once per loaded space object."""
    hit = _KEYS.get(id(space))
    if hit is None or hit[0] is not space:
        hit = (space, space.content_hash)
        _KEYS[id(space)] = hit
    return hit[1]


def _reference_libraries(library_path: str | os.PathLike | None) -> list:
    """The libraries a reference may be built from: the given library.json, then the bundled one."""
    from adv3d_runner.shapes.library import DEFAULT_LIBRARY, load_library

    paths = [Path(library_path).expanduser().resolve()] if library_path else []
    if DEFAULT_LIBRARY.is_file() and DEFAULT_LIBRARY.resolve() not in paths:
        paths.append(DEFAULT_LIBRARY.resolve())
    return [load_library(p) for p in paths]


def build_reference_for(space, library_path: str | os.PathLike | None = None) -> Any:
    """Build ``space``'s reference here from the first library holding all its assets (the given
    one, then the bundled one) and keep it (memory and the runner's disk cache); blocking.

    Raises:
        Adv3dError: no library holds the space's assets (named), or a library is unreadable.
    """
    from adv3d_runner.shapes import realism
    from adv3d_runner.shapes.library import load_library

    ref = realism.build_reference(load_library(_holding_library(space, library_path)), space)
    realism.cache_reference(space, ref)
    _REFERENCES[space_key(space)] = ref
    return ref


#: Builds a reference in a child Python (argv: shape space .npz, library.json); the child's
#: work never competes with Blender's UI thread for the GIL.
_BUILD_SCRIPT = """import sys
from adv3d_runner.errors import Adv3dError
from adv3d_runner.shapes import realism
from adv3d_runner.shapes.library import load_library
from adv3d_runner.shapes.shape_space import ShapeSpace
try:
    space = ShapeSpace.load(sys.argv[1])
    realism.cache_reference(space, realism.build_reference(load_library(sys.argv[2]), space))
except (Adv3dError, OSError, KeyError) as exc:
    sys.exit(f"adv3d: error: {exc}")
"""


def _holding_library(space, library_path) -> Path:
    """The first library.json holding all of ``space``'s assets (the given one, then the bundled one).

    Raises:
        Adv3dError: none does (named, with what each lacks).
    """
    missing = []
    for library in _reference_libraries(library_path):
        lacking = sorted(set(space.asset_ids) - set(library.ids()))
        if not lacking:
            return library.root / "library.json"
        missing.append(f"{library.root / 'library.json'} lacks {', '.join(lacking[:3])}"
                       + (f" and {len(lacking) - 3} more" if len(lacking) > 3 else ""))
    raise Adv3dError("no realism reference for this shape space: no library holds its assets ("
                     + ("; ".join(missing) or "no library") + "); load the library it was built from")


def _build_in_background(space, key: str, library_path) -> None:
    """Thread body: build the reference in a child Python when the space's file is known (this
    thread only waits), else here; a failure is kept for the panel."""
    import subprocess
    import sys

    try:
        lib_file = _holding_library(space, library_path)
        space_file = _PATHS.get(id(space), (None, None))
        if space_file[0] is space:
            env = dict(os.environ)
            env.pop("PYTHONHOME", None)
            env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
            out = subprocess.run([sys.executable, "-c", _BUILD_SCRIPT, str(space_file[1]), str(lib_file)],
                                 capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
            from adv3d_runner.shapes import realism

            ref = realism.known_reference(space) if out.returncode == 0 else None
            if ref is None:
                lines = [ln for ln in (out.stderr or "").splitlines() if ln.strip()]
                raise Adv3dError(lines[-1] if lines else f"reference build exited {out.returncode}")
            _REFERENCES[key] = ref
        else:
            build_reference_for(space, lib_file)
    except Exception as exc:  # reported in the panel on the next slider move
        _FAILED[key, str(library_path or "")] = (str(exc) if isinstance(exc, Adv3dError)
                                                 else f"{type(exc).__name__}: {exc}")


def _reference_beside(space) -> Any:
    """A ``realism_reference.npz`` in the space file's folder built for it (the extension's
    starter space carries its reference so), else None."""
    from adv3d_runner.shapes import realism

    hit = _PATHS.get(id(space))
    if hit is None or hit[0] is not space:
        return None
    path = hit[1].parent / "realism_reference.npz"
    try:
        ref = realism.load_reference(path) if path.is_file() else None
    except Adv3dError:
        return None
    return ref if ref is not None and ref.matches(space) else None


def realism_reference(space, library_path: str | os.PathLike | None = None, wait: bool = False) -> Any:
    """The realism reference of ``space``: a known one at once; otherwise its background build is
    started (from ``library_path``, else the bundled library) and :class:`ReferencePending`
    raised until it is done (``wait``: block until it is).

    Raises:
        ReferencePending: still building (not ``wait``).
        Adv3dError: it cannot be built (no library holds the space's assets).
    """
    import threading

    from adv3d_runner.shapes import realism

    key = space_key(space)
    ref = _REFERENCES.get(key)
    if ref is not None:
        return ref
    thread = _BUILDS.get(key)
    if thread is None or not thread.is_alive():
        if (key, str(library_path or "")) in _FAILED:  # another library may hold the assets: tried anew
            raise Adv3dError(_FAILED[key, str(library_path or "")])
        ref = realism.known_reference(space) or _reference_beside(space)
        if ref is not None:
            _REFERENCES[key] = ref
            return ref
        thread = threading.Thread(target=_build_in_background, args=(space, key, library_path),
                                  name="adv3d realism reference", daemon=True)
        _BUILDS[key] = thread
        thread.start()
    if wait:
        thread.join()
        return realism_reference(space, library_path)
    raise ReferencePending("building the realism reference of this shape space in the background "
                           "(once per space: it is cached)")


def reference_building() -> bool:
    """Whether a reference is being built (the panel polls until it is done)."""
    return any(t.is_alive() for t in _BUILDS.values())


def clear_reference_state() -> None:
    """Forget references, builds and failures of this session, the runner's in-process ones too
    (the disk cache stays): what a new Blender session starts from."""
    from adv3d_runner.shapes import realism

    for thread in _BUILDS.values():
        thread.join()
    realism._CACHE.clear()
    _REFERENCES.clear()
    _BUILDS.clear()
    _FAILED.clear()
    _KEYS.clear()


def _flag(ok: bool) -> str:
    return "ok" if ok else "OUT"


def live_realism(space, u: np.ndarray, vertices: np.ndarray, faces: np.ndarray, vehicle_class: str | None = None,
                 library_path: str | os.PathLike | None = None) -> list[str]:
    """The realism lines the Shape space panel shows while a slider moves: the cheap measures
    without the nearest-CAD-model search (``quick_measures(chamfer=False)``: JSD, Mahalanobis,
    dimensions against the class; docs/realism.md "Per query and live").

    Raises:
        ReferencePending: the space's reference is still being built (the lines say so).
    """
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
    Blender) and the lines the panel shows for it (waits for a reference being built)."""
    from adv3d_runner.shapes import realism

    ref = realism_reference(space, library_path, wait=True)
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
