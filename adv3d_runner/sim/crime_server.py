"""CriMe server: criticality measures of a CommonRoad scenario, computed by CommonRoad's CriMe
(``commonroad-crime``) in **its own virtual environment** (docs/attack.md, "Criticality (CriMe)").

CriMe cannot share adv3d's environment: ``pip install commonroad-crime`` there would replace
numpy 1.26 by numpy 2 (Blender's bpy pins numpy < 2) and commonroad-io 2026.1 by 2024.3; with
both pinned, pip falls back to commonroad-crime 0.4.3 and downgrades matplotlib to 3.8. So this
file is run as a script by that environment's interpreter (``examples/crime/install.sh`` builds
it) and imports nothing of ``adv3d_runner``; :mod:`adv3d_runner.sim.criticality` starts it and
talks to it:

    <crime venv>/bin/python -P adv3d_runner/sim/crime_server.py

Protocol, one JSON object per line (``Infinity`` / ``NaN`` allowed: both ends are Python):

* first line out: ``{"ready": true, "versions": {"commonroad-crime": ..., "commonroad-io": ...}}``
  (or ``{"ready": false, "error": ...}`` when CriMe cannot be imported);
* each line in: ``{"xml": PATH, "ego_id": ID, "plain": bool (optional: without the shortcuts
  below, for tests), "vehicles": [ID, ...] (optional, default every
  other dynamic obstacle), "measures": [NAME, ...] (optional, default :data:`PAIR_MEASURES` +
  :data:`EGO_MEASURES`; ``DCE`` too), "time_steps": [k, ...] (optional, default every time
  step of the ego's trajectory), "ego_time_steps": [k, ...] (optional: the time steps of the ego
  measures, default ``time_steps``)}``;
* each line out: ``{"ok": true, "time_steps": [k0, ...], "ego_time_steps": [...], "pairs": {NAME:
  {VID: [value per time step]}}, "ego": {NAME: [value per ego time step]}, "dce": {VID: [distance
  m, time step]}, "seconds": {NAME: s}}`` or ``{"ok": false, "error": MESSAGE}``.

Values are CriMe's, unchanged: ``compute(vehicle_id, time_step)`` of each measure for every
(vehicle, time step); NaN where CriMe has no value (the vehicle absent),
``Infinity`` where the measure says "never" (no leader in the lane, not closing). Everything
CriMe prints goes to stderr; stdout carries only the protocol.

Shortcuts, results unchanged (``"plain": true`` turns them off; tests/test_criticality.py
compares): CriMe smooths a lanelet's three polylines (a B-spline) every time it asks a lanelet's
orientation, i.e. per vehicle and time step: the smoothing is a pure function of the vertices,
so it is cached per polyline. Every pair measure first asks whether the vehicle is in the ego's
lanelets (``check_in_same_lanelet``) and has a fixed answer when not: asked once per (vehicle,
time step) here, and vehicles never there are left out of the scenario the measures copy. BTN
is CriMe's formula on the ALongReq values (BTN would compute them again). TTB is infinite
without a TTC* collision (CriMe's TTM), so it is not built then.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
import traceback

#: CriMe measures computed per (other vehicle, time step), by class name
PAIR_MEASURES = ("TTC", "THW", "HW", "ALongReq", "BTN")
#: CriMe measures of the ego against every obstacle at once, per time step
EGO_MEASURES = ("TTCStar", "TTB")


#: a request with ``"plain": true`` runs CriMe without this file's shortcuts (tests compare)
_PLAIN = {"on": False}


def _cached_smoothing(solver) -> None:
    """Cache ``commonroad_crime.utility.solver.smoothing_reference_path`` per (polyline, smooth
    factor, weight): it is deterministic, and CriMe calls it on the same lanelet vertices for
    every vehicle and time step. Callers get a copy of the cached polyline."""
    import numpy as np

    original = solver.smoothing_reference_path
    cache: dict = {}

    def smoothing_reference_path(reference_path, smooth_factor=None, weight_coefficient=None):
        if _PLAIN["on"]:
            return original(reference_path, smooth_factor, weight_coefficient)
        arr = np.ascontiguousarray(reference_path, dtype=np.float64)
        key = (arr.shape, arr.tobytes(), smooth_factor, weight_coefficient)
        if key not in cache:
            if len(cache) > 4096:
                cache.clear()
            cache[key] = np.array(original(arr, smooth_factor, weight_coefficient), dtype=np.float64)
        return cache[key].copy()

    solver.smoothing_reference_path = smoothing_reference_path


def _number(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


#: what CriMe's pair measures answer for a vehicle outside the ego's lanelets (their
#: ``_except_obstacle_in_same_lanelet`` branch; TTC through its HW)
NOT_SAME_LANELET = {"TTC": math.inf, "THW": math.inf, "HW": math.inf, "ALongReq": 0.0}


def _same_lanelet(scenario, ego, others, steps) -> dict:
    """vehicle id -> per time step: True / False (CriMe's ``check_in_same_lanelet`` of the ego
    and the vehicle, which every pair measure asks first), None when either is absent. Asked
    once here instead of once per measure; a False skips the measure with the value CriMe gives
    that case (:data:`NOT_SAME_LANELET`)."""
    from commonroad_crime.utility.general import check_in_same_lanelet

    out = {}
    network = scenario.lanelet_network
    for vid in others:
        other = scenario.obstacle_by_id(int(vid))
        flags = []
        for k in steps:
            if ego.state_at_time(k) is None or other.state_at_time(k) is None:
                flags.append(None)
            else:
                flags.append(bool(check_in_same_lanelet(network, ego, other, k)))
        out[vid] = flags
    return out


def _without(scenario, drop: list, ego_id: int):
    """A CriMe configuration of a copy of ``scenario`` without the obstacles ``drop`` (those
    never in the ego's lanelets: every pair measure has its fixed answer for them, and each
    measure deep-copies the scenario it is given)."""
    import copy

    from commonroad_crime.data_structure.configuration import CriMeConfiguration

    reduced = copy.copy(scenario) if not drop else copy.deepcopy(scenario)
    for vid in drop:
        reduced.remove_obstacle(reduced.obstacle_by_id(int(vid)))
    config = CriMeConfiguration()
    config.update(ego_id=ego_id, sce=reduced)
    return config


def evaluate(request: dict, measures_by_name: dict) -> dict:
    """One request (see the module docstring) -> its answer."""
    _PLAIN["on"] = bool(request.get("plain"))
    try:
        return _evaluate(request, measures_by_name, _PLAIN["on"])
    finally:
        _PLAIN["on"] = False


def _evaluate(request: dict, measures_by_name: dict, plain: bool) -> dict:
    from commonroad.common.file_reader import CommonRoadFileReader
    from commonroad_crime.data_structure.configuration import CriMeConfiguration

    scenario, _ = CommonRoadFileReader(str(request["xml"])).open(lanelet_assignment=True)
    ego_id = int(request["ego_id"])
    config = CriMeConfiguration()
    config.update(ego_id=ego_id, sce=scenario)
    ego = scenario.obstacle_by_id(ego_id)
    if ego is None:
        raise ValueError(f"no obstacle {ego_id} (the ego) in {request['xml']}")
    first = int(ego.initial_state.time_step)
    last = int(ego.prediction.final_time_step) if ego.prediction is not None else first
    steps = [int(k) for k in request.get("time_steps") or range(first, last + 1)]
    ego_steps = [int(k) for k in request.get("ego_time_steps") or steps]
    others = request.get("vehicles")
    if others is None:
        others = [o.obstacle_id for o in scenario.dynamic_obstacles if o.obstacle_id != ego_id]
    names = request.get("measures") or list(PAIR_MEASURES + EGO_MEASURES)
    unknown = [n for n in names if n not in measures_by_name]
    if unknown:
        raise ValueError(f"unknown measure(s) {unknown}; known: {sorted(measures_by_name)}")
    pairs: dict = {}
    ego_values: dict = {}
    dce: dict = {}
    same = pair_config = None
    seconds: dict = {}
    cpu0 = time.process_time()
    for name in names:
        t0 = time.perf_counter()
        if name == "BTN" and not plain:
            continue  # below, from ALongReq
        no_contact = "TTCStar" in ego_values and not any(math.isfinite(v) for v in ego_values["TTCStar"])
        if not plain and name == "TTB" and no_contact:
            ego_values[name] = [math.inf] * len(ego_steps)  # TTM: no collision (TTC* inf) -> inf
            seconds[name] = round(time.perf_counter() - t0, 4)
            continue
        if name in EGO_MEASURES or name == "DCE":
            measure = measures_by_name[name](config)
        else:
            if same is None and plain:
                same = {v: [True if ego.state_at_time(k) is not None
                            and scenario.obstacle_by_id(int(v)).state_at_time(k) is not None else None
                            for k in steps] for v in others}
                pair_config = config
            elif same is None:
                same = _same_lanelet(scenario, ego, others, steps)
                pair_config = _without(scenario, [v for v in others if not any(same[v])], ego_id)
            measure = measures_by_name[name](pair_config)
        if name in EGO_MEASURES:
            ego_values[name] = [_number(measure.compute(time_step=k, verbose=False)) for k in ego_steps]
        elif name == "DCE":
            # the closest encounter along the trajectories, once per vehicle from its first time
            # step with the ego (CriMe's DCE from a time step is the minimum over the later ones)
            for vid in others:
                obstacle = scenario.obstacle_by_id(int(vid))
                k0 = max(steps[0], int(obstacle.initial_state.time_step))
                if k0 > steps[-1]:
                    continue
                measure.time_dce = math.inf  # CriMe keeps it from the previous call
                value = _number(measure.compute(vehicle_id=int(vid), time_step=k0, verbose=False))
                dce[str(vid)] = [value, None if measure.time_dce == math.inf else int(measure.time_dce)]
        else:
            per = {}
            for vid in others:  # vehicle-major: CriMe copies the other vehicle when it changes
                per[str(vid)] = [_number(measure.compute(vehicle_id=int(vid), time_step=k, verbose=False))
                                 if flag else (math.nan if flag is None else NOT_SAME_LANELET[name])
                                 for k, flag in zip(steps, same[vid])]
            pairs[name] = per
        seconds[name] = round(time.perf_counter() - t0, 4)
    if "BTN" in names and not plain:
        # CriMe's BTN.compute, on the ALongReq values already computed: int_round(a_long_req /
        # -a_lon_max, 4) (a_lon_max: the configuration's maximum braking, 11.5 m/s^2)
        from commonroad_crime.utility.general import int_round

        if "ALongReq" not in pairs:
            raise ValueError("BTN needs ALongReq in the same request")
        a_max = float(config.vehicle.curvilinear.a_lon_max)
        pairs["BTN"] = {vid: [v if math.isnan(v) else int_round(v / -a_max, 4) for v in vals]
                        for vid, vals in pairs["ALongReq"].items()}
    seconds["cpu"] = round(time.process_time() - cpu0, 4)
    return {"ok": True, "time_steps": steps, "ego_time_steps": ego_steps, "pairs": pairs, "ego": ego_values,
            "dce": dce, "seconds": seconds}


def main() -> int:
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # CriMe prints its warnings: keep them off the protocol
    sys.stdout = sys.stderr

    def say(obj: dict) -> None:
        proto.write(json.dumps(obj) + "\n")
        proto.flush()

    try:
        import logging
        import warnings
        from importlib.metadata import version

        logging.disable(logging.WARNING)
        warnings.filterwarnings("ignore")
        import commonroad_crime.utility.solver as solver
        from commonroad_crime.measure import BTN, DCE, HW, THW, TTB, TTC, ALongReq, TTCStar

        _cached_smoothing(solver)
        measures_by_name = {"TTC": TTC, "THW": THW, "HW": HW, "ALongReq": ALongReq, "BTN": BTN, "DCE": DCE,
                            "TTCStar": TTCStar, "TTB": TTB}
        versions = {p: version(p) for p in ("commonroad-crime", "commonroad-io", "commonroad-drivability-checker",
                                           "numpy")}
    except Exception as exc:  # noqa: BLE001 - reported to the client, which says "not available"
        say({"ready": False, "error": f"{type(exc).__name__}: {exc}"})
        return 1
    say({"ready": True, "versions": versions})
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            say(evaluate(json.loads(line), measures_by_name))
        except Exception as exc:  # noqa: BLE001 - one bad request must not end the server
            traceback.print_exc()
            say({"ok": False, "error": f"{type(exc).__name__}: {exc}"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
