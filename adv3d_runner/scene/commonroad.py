"""Import CommonRoad scenarios (recorded traffic) as scenes, through commonroad-io.

* Lanelets -> lanes: centre vertices, width per vertex (distance between the lanelet's left and
  right bounds), left/right neighbour only when it drives in the same direction, successors.
  Speed limits are kept when the scenario has a max-speed traffic sign, else null.
* Dynamic obstacles -> actors: per-frame x, y, yaw, speed from the initial state and the
  trajectory, resampled to 0.1 s when the scenario's dt differs (linear in x, y, speed;
  unwrapped yaw). Class from the obstacle type (cars split into hatchback / sedan / suv by
  footprint, see ``_car_class``); height (not in CommonRoad) from the class.
* Ego rule: ``--ego ID`` when given; else the car with a track over the whole recording that has
  the most vehicles ahead of it (same or adjacent lane, within 50 m) in the first frame,
  preferring cars in a lane with neighbours on both sides; ties -> smallest obstacle id. The
  ego is removed from the actors. (CommonRoad's planning problem has only an initial state,
  no logged trajectory, so it is not used as ego.)
* Length: ``seconds`` (default: the recording). A recording shorter than asked is an error
  unless ``extend=True``: then every vehicle present at the last recorded frame, and the ego,
  keeps driving along its nearest lane (IDM car following on the lane chain, no lane changes;
  a vehicle between lanes drifts to the nearest lane centre within 2 s) and the added frames
  are flagged ``synthetic`` in its track.

Provenance goes into ``source``: the benchmark id, file, authors, affiliation, tags, the ego
rule, the number of recorded frames; licence BSD-3-Clause and the NGSIM / TUM / OSM attribution.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..errors import ConfigError, FileFormatError, UsageError
from ..dynamics.traffic import IDMParams, Traffic
from ..geometry.angles import wrap_angle
from . import lanes as lg
from .generate import EGO_WHEELBASE
from .schema import (MAX_COORD, MAX_DT, MAX_FRAMES, MAX_SIZE, MAX_SPEED, Actor, Background, Barrier, Ego, Lane,
                     Scene, Source, Track, default_sensors)

DT = 0.1
MIN_SCENARIO_DT = 1e-3  # s: recordings are sampled at 10-100 Hz; a smaller step is a broken file
LICENCE = "BSD-3-Clause (CommonRoad scenario; see scenes/real/LICENSE.txt)"
ATTRIBUTION = ("Vehicle trajectories: NGSIM US-101 dataset, U.S. Department of Transportation, Federal "
               "Highway Administration (FHWA), Next Generation Simulation program. Scenario conversion: "
               "CommonRoad benchmark, Technical University of Munich (TUM), Cyber-Physical Systems group. "
               "Road network: OpenStreetMap contributors (ODbL).")
CLASS_HEIGHT = {"hatchback": 1.48, "sedan": 1.45, "suv": 1.75, "truck": 3.8, "bus": 3.2,
                "motorcycle": 1.3, "other": 1.6, "van": 2.0}


#: vehicle classes that can be the ego (a car; the rule of ``_pick_ego`` and of
#: ``bench/real_train_egos.py``, which takes every such car of a recording in turn)
EGO_CLASSES = ("sedan", "hatchback", "suv")


def _car_class(length: float, width: float) -> str:
    if length >= 5.3 or width >= 2.05:
        return "suv"
    if length < 4.3:
        return "hatchback"
    return "sedan"


def _obstacle_class(obstacle) -> str:
    kind = str(obstacle.obstacle_type.value).lower()
    shape = obstacle.obstacle_shape
    if kind in ("car", "taxi", "priorityvehicle", "parkedvehicle"):
        return _car_class(float(shape.length), float(shape.width))
    return {"truck": "truck", "bus": "bus", "motorcycle": "motorcycle", "bicycle": "other"}.get(kind, "other")


def _header(path: Path) -> dict:
    """Attributes of the root <commonRoad> element (authors, source, benchmark id, ...). The file
    is read bounded (a regular file of at most ``fileio.MAX_JSON_BYTES``) before parsing."""
    from ..fileio import read_bytes

    raw = read_bytes(path, what="CommonRoad XML file")
    try:
        root = ET.fromstring(raw)
    except ET.ParseError as exc:
        raise FileFormatError(path, "$", "a CommonRoad XML file", str(exc)) from None
    _check_xml_numbers(root, path)
    return dict(root.attrib)


# Bounds of the numbers of a CommonRoad XML by the element that holds them (its parent for
# <exact>, <intervalStart>, <intervalEnd>); checked before commonroad-io parses the file:
# commonroad-io wraps an orientation by subtracting 2 pi in a loop, which never ends for 1e20.
_XML_BOUNDS = {"orientation": 1e3, "time": 1e7, "velocity": 1e3, "acceleration": 1e3, "yawRate": 1e3,
               "slipAngle": 1e3, "x": MAX_COORD, "y": MAX_COORD, "length": MAX_SIZE, "width": MAX_SIZE,
               "radius": MAX_SIZE}


def _check_xml_numbers(root: ET.Element, path: Path) -> None:
    """Every number of the scenario's states, bounds and shapes is finite and within
    :data:`_XML_BOUNDS`, and ``timeStepSize`` is a number (``FileFormatError`` naming the
    element, e.g. ``obstacle[@id=3]/initialState/orientation/exact``)."""
    try:
        float(root.get("timeStepSize", "0.1"))
    except ValueError:
        raise FileFormatError(path, "commonRoad/@timeStepSize", "a number", root.get("timeStepSize")) from None
    stack = [(root, "commonRoad", None)]
    while stack:
        el, where, parent = stack.pop()
        children = list(el)
        for child in children:
            ident = child.get("id")
            stack.append((child, f"{where}/{child.tag}" + (f"[@id={ident}]" if ident else ""), el.tag))
        if children or el.text is None or not el.text.strip():
            continue
        key = parent if el.tag in ("exact", "intervalStart", "intervalEnd") else el.tag
        if key not in _XML_BOUNDS:
            continue
        try:
            value = float(el.text)
        except ValueError:
            raise FileFormatError(path, where, "a number", el.text.strip()[:40]) from None
        if not np.isfinite(value) or abs(value) > _XML_BOUNDS[key]:
            raise FileFormatError(path, where, f"a finite number within +-{_XML_BOUNDS[key]:g}", el.text.strip()[:40])


def _lanes(network) -> list[Lane]:
    out = []
    speed = _speed_limits(network)
    for ll in network.lanelets:
        centre = np.asarray(ll.center_vertices, dtype=np.float64)
        width = np.hypot(*(np.asarray(ll.left_vertices) - np.asarray(ll.right_vertices)).T)
        left = ll.adj_left if (ll.adj_left is not None and ll.adj_left_same_direction) else None
        right = ll.adj_right if (ll.adj_right is not None and ll.adj_right_same_direction) else None
        out.append(Lane(id=int(ll.lanelet_id), centerline=centre, width=width, left=left, right=right,
                        successors=[int(s) for s in ll.successor], speed_limit=speed.get(ll.lanelet_id)))
    return out


def _speed_limits(network) -> dict[int, float]:
    """lanelet id -> max speed (m/s) from MAX_SPEED traffic signs, where present."""
    out: dict[int, float] = {}
    signs = {s.traffic_sign_id: s for s in (network.traffic_signs or [])}
    for ll in network.lanelets:
        for sid in ll.traffic_signs or ():
            sign = signs.get(sid)
            if sign is None:
                continue
            for el in sign.traffic_sign_elements:
                if "max_speed" in str(el.traffic_sign_element_id.name).lower() and el.additional_values:
                    try:
                        v = float(el.additional_values[0])
                    except ValueError:
                        continue
                    if np.isfinite(v) and 0 < v <= MAX_SPEED:  # anything else: unknown limit
                        out[ll.lanelet_id] = v
    return out


def _states(obstacle, scenario_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(times (n,) in s, values (n, 4): x, y, yaw, speed) of an obstacle."""
    states = [obstacle.initial_state] + list(obstacle.prediction.trajectory.state_list if obstacle.prediction else [])
    t = np.array([s.time_step for s in states], dtype=np.float64) * scenario_dt
    vals = np.array([[s.position[0], s.position[1], s.orientation, getattr(s, "velocity", 0.0) or 0.0] for s in states], dtype=np.float64)
    order = np.argsort(t, kind="stable")
    return t[order], vals[order]


def _resample(t: np.ndarray, vals: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Interpolate (x, y, yaw, speed) at ``frames * DT``; yaw unwrapped first."""
    vals = vals.copy()
    vals[:, 2] = np.unwrap(vals[:, 2])
    ft = frames * DT
    out = np.stack([np.interp(ft, t, vals[:, k]) for k in range(4)], axis=1)
    out[:, 2] = wrap_angle(out[:, 2])
    out[:, 3] = np.maximum(out[:, 3], 0.0)
    return out


def _chain(lanes: dict[int, Lane], start: int, min_length: float = 1500.0) -> np.ndarray:
    """Centre line of ``start`` followed by first successors (cycle-safe), as one polyline."""
    pts = [lanes[start].centerline]
    seen = {start}
    cur = start
    total = lg.length(pts[0])
    while lanes[cur].successors and total < min_length:
        nxt = lanes[cur].successors[0]
        if nxt in seen or nxt not in lanes:
            break
        seen.add(nxt)
        pts.append(lanes[nxt].centerline)
        total += lg.length(lanes[nxt].centerline)
        cur = nxt
    return lg.clean_polyline(np.concatenate(pts))


def _root(lanes: dict[int, Lane], lane_id: int) -> int:
    """First lane of the chain through ``lane_id`` (walk back along predecessors, smallest id
    first), so vehicles in consecutive lanelets of one physical lane share one chain."""
    preds: dict[int, list[int]] = {}
    for lane in lanes.values():
        for succ in lane.successors:
            preds.setdefault(succ, []).append(lane.id)
    seen = {lane_id}
    while preds.get(lane_id):
        prev = min(preds[lane_id])
        if prev in seen:
            break
        seen.add(prev)
        lane_id = prev
    return lane_id


def _nearest_lane(lanes: list[Lane], xy: np.ndarray, yaw: float) -> int:
    """Id of the lane whose centre line is nearest to ``xy`` among lanes heading within 60
    degrees of ``yaw`` (any lane if none does)."""
    best, best_cost = lanes[0].id, np.inf
    for lane in lanes:
        s, d, h = lg.project(lane.centerline, xy)
        L = lg.length(lane.centerline)
        outside = max(0.0, -s, s - L)  # prefer lanes the point actually lies along
        cost = abs(d) + 2.0 * outside + (100.0 if abs(wrap_angle(h - yaw)) > np.pi / 3 else 0.0)
        if cost < best_cost:
            best, best_cost = lane.id, cost
    return best


def _extend(tracks: dict[int, np.ndarray], lengths: dict[int, float], last: int, frames: int,
            lanes: list[Lane]) -> dict[int, np.ndarray]:
    """Drive every vehicle valid at frame ``last`` on to ``frames - 1`` along its lane chain
    (IDM following the vehicle ahead on the same chain). Returns the extra rows per id."""
    by_id = {lane.id: lane for lane in lanes}
    ids = [i for i, tr in tracks.items() if np.isfinite(tr[last, 0])]
    chains: dict[int, np.ndarray] = {}
    key_of: dict[int, int] = {}
    s0, d0 = {}, {}
    for i in ids:
        x, y, yaw, _ = tracks[i][last]
        lane_id = _root(by_id, _nearest_lane(lanes, np.array([x, y]), yaw))
        chains.setdefault(lane_id, _chain(by_id, lane_id))
        key_of[i] = lane_id
        s, d, _ = lg.project(chains[lane_id], np.array([x, y]))
        s0[i], d0[i] = float(s), float(d)
    keys = sorted(chains)
    traffic = Traffic(lane_start=np.full(len(keys), -np.inf), lane_end=np.full(len(keys), np.inf),
                      idm=IDMParams(), lane_changes=False)
    for i in ids:
        v = float(tracks[i][last, 3])
        traffic.add(s0[i], keys.index(key_of[i]), v, lengths[i], max(1.05 * v, 3.0))
    out = {i: np.zeros((frames - last - 1, 4)) for i in ids}
    for f in range(frames - last - 1):
        traffic.step(DT)
        for j, i in enumerate(ids):
            chain = chains[key_of[i]]
            # drift to the lane centre within 2 s: a vehicle caught mid lane change finishes
            # it instead of driving on the lane line (where it could overlap a neighbour)
            u = min(1.0, (f + 1) * DT / 2.0)
            x, y, h = lg.pose_at(chain, traffic.s[j], d0[i] * (1.0 - u * u * (3.0 - 2.0 * u)))
            out[i][f] = (x, y, h, traffic.v[j])
    return out


def import_commonroad(path: str | Path, seconds: float | None = None, extend: bool = False,
                      ego_id: int | None = None, ego_rank: int = 0) -> Scene:
    """Convert a CommonRoad XML scenario into a Scene (see module docstring).

    ``ego_rank`` k > 0 takes the (k+1)-th car of the ego rule's order instead of the first, so
    the variants of one recording (same traffic, different planning problems) can become
    different scenes.

    Raises:
        FileFormatError: unreadable scenario, or no usable ego.
        ConfigError: ``seconds`` longer than the recording without ``extend``.
    """
    from commonroad.common.file_reader import CommonRoadFileReader

    path = Path(path)
    header = _header(path)
    try:
        scenario, _ = CommonRoadFileReader(str(path)).open()
    except Exception as exc:  # commonroad-io raises assorted errors on bad files
        raise FileFormatError(path, "$", "a CommonRoad scenario readable by commonroad-io", str(exc)) from None
    sdt = float(scenario.dt)
    _check_scenario(path, scenario)
    lanes = _lanes(scenario.lanelet_network)
    if not lanes:
        raise FileFormatError(path, "$.lanelet", "at least one lanelet")
    obstacles = list(scenario.dynamic_obstacles)
    if not obstacles:
        raise FileFormatError(path, "$.dynamicObstacle", "at least one dynamic obstacle")
    raw = {o.obstacle_id: _states(o, sdt) for o in obstacles}
    t_end = max(t[-1] for t, _ in raw.values())
    recorded = int(np.floor(t_end / DT + 1e-6)) + 1
    frames = recorded if seconds is None else int(round(seconds / DT))
    if frames < 1:
        raise UsageError("--seconds must be at least one frame (0.1 s)")
    if frames > recorded and not extend:
        raise UsageError(f"{path.name} records {recorded} frames ({recorded * DT:.1f} s) but {frames} were asked; "
                          "pass --extend to extrapolate (the added frames are marked synthetic)")
    n_rec = min(frames, recorded)
    # per obstacle: (recorded frames, 4) with NaN where not present
    tracks: dict[int, np.ndarray] = {}
    for oid, (t, vals) in raw.items():
        arr = np.full((n_rec, 4), np.nan)
        f = np.arange(n_rec)
        inside = (f * DT >= t[0] - 1e-6) & (f * DT <= t[-1] + 1e-6)
        if inside.any():
            arr[inside] = _resample(t, vals, f[inside])
        tracks[oid] = arr
    info = {o.obstacle_id: o for o in obstacles}
    lengths = {oid: float(info[oid].obstacle_shape.length) for oid in tracks}
    ego_oid, rule = _pick_ego(tracks, info, lanes, ego_id, path, ego_rank)
    synthetic_from = n_rec
    if frames > n_rec:
        more = _extend(tracks, lengths, n_rec - 1, frames, lanes)
        for oid in tracks:
            pad = np.full((frames - n_rec, 4), np.nan)
            if oid in more:
                pad = more[oid]
            tracks[oid] = np.concatenate([tracks[oid], pad])
    # ego
    et = tracks.pop(ego_oid)
    eshape = info[ego_oid].obstacle_shape
    ecls = _obstacle_class(info[ego_oid])
    synth = np.arange(frames) >= synthetic_from
    ego = Ego(dimensions=(float(eshape.length), float(eshape.width), CLASS_HEIGHT.get(ecls, 1.5)),
              wheelbase=min(EGO_WHEELBASE, 0.6 * float(eshape.length)),
              track=Track(x=et[:, 0], y=et[:, 1], yaw=et[:, 2], speed=et[:, 3], synthetic=synth if synth.any() else None),
              sensors=default_sensors())
    actors = []
    for oid in sorted(tracks):
        arr = tracks[oid]
        ok = np.isfinite(arr[:, 0])
        if not ok.any():
            continue
        idx = np.flatnonzero(ok)
        a, b = idx[0], idx[-1] + 1
        seg = arr[a:b].copy()
        valid = ok[a:b]
        seg[~valid] = 0.0  # placeholders in gaps (never used: valid is 0 there)
        syn = (np.arange(a, b) >= synthetic_from)
        cls = _obstacle_class(info[oid])
        shape = info[oid].obstacle_shape
        actors.append(Actor(id=int(oid), cls=cls,
                            dimensions=(float(shape.length), float(shape.width), CLASS_HEIGHT.get(cls, 1.5)),
                            track=Track(x=seg[:, 0], y=seg[:, 1], yaw=seg[:, 2], speed=seg[:, 3], start=int(a),
                                        valid=None if valid.all() else valid, synthetic=syn if syn.any() else None)))
    bench = header.get("benchmarkID") or str(scenario.scenario_id)
    details = {
        "benchmark_id": bench, "file": path.name, "commonroad_version": header.get("commonRoadVersion"),
        "author": header.get("author"), "affiliation": header.get("affiliation"), "data_source": header.get("source"),
        "date": header.get("date"), "tags": sorted(str(t.value) for t in (scenario.tags or [])),
        "scenario_dt": sdt, "recorded_frames": int(n_rec), "extended_frames": int(frames - n_rec),
        "ego_obstacle_id": int(ego_oid), "ego_rule": rule, "layout": "real",
    }
    background = Background(shoulder_left=1.0, shoulder_right=2.5, ground_margin=30.0, lane_markings=True,
                            barriers=_edge_barriers(lanes))
    scene = Scene(id=f"commonroad-{bench}", source=Source("commonroad", details, LICENCE, ATTRIBUTION), dt=DT,
                  frames=frames, lanes=lanes, background=background, ego=ego, actors=actors)
    # the scene contract, checked here so a broken scenario (a lanelet naming a missing
    # neighbour, an id that is not a file name) is an error naming the XML, before any writing
    return Scene.from_dict(scene.to_dict(), path)


def _check_scenario(path: Path, scenario) -> None:
    """Refuse what would make a broken or silently wrong scene, before anything is built: a
    time step that is not a positive finite number (``timeStepSize="0"`` made one-frame scenes),
    non-finite or out-of-range coordinates, sizes, speeds and time steps (the scene contract's
    bounds, ``scene.schema.MAX_*``). Fields are named as in the XML.

    Raises:
        FileFormatError: naming the file and the element.
    """
    def bad(field: str, expected: str, got) -> None:
        raise FileFormatError(path, field, expected, got)

    dt = float(scenario.dt)
    if not (np.isfinite(dt) and MIN_SCENARIO_DT <= dt <= MAX_DT):  # 1e-320 s would fold a recording into one frame
        bad("commonRoad/@timeStepSize", f"a time step in [{MIN_SCENARIO_DT:g}, {MAX_DT:g}] s", scenario.dt)
    coord = f"finite coordinates within +-{MAX_COORD:g} m"
    for ll in scenario.lanelet_network.lanelets:
        for name in ("left_vertices", "right_vertices", "center_vertices"):
            v = np.asarray(getattr(ll, name), dtype=np.float64)
            if v.ndim != 2 or len(v) < 2 or not np.isfinite(v).all() or np.abs(v).max() > MAX_COORD:
                bad(f"lanelet[@id={ll.lanelet_id}]/{name.split('_')[0]}Bound", coord + " (at least 2 points)",
                    v.tolist()[:2])
    for o in scenario.dynamic_obstacles:
        where = f"dynamicObstacle[@id={o.obstacle_id}]"
        shape = o.obstacle_shape
        for name in ("length", "width"):
            v = getattr(shape, name, None)
            if v is None or not np.isfinite(float(v)) or not 0 < float(v) <= MAX_SIZE:
                bad(f"{where}/shape/rectangle/{name}", f"a rectangle {name} in (0, {MAX_SIZE:g}] m", v)
        states = [o.initial_state] + list(o.prediction.trajectory.state_list if o.prediction else [])
        for st in states:
            step = int(st.time_step)
            if not 0 <= step * dt / DT <= MAX_FRAMES:
                bad(f"{where}/state[time={step}]", f"a time step within {MAX_FRAMES} frames of 0.1 s", step)
            pos = np.asarray(st.position, dtype=np.float64)
            if pos.shape != (2,) or not np.isfinite(pos).all() or np.abs(pos).max() > MAX_COORD:
                bad(f"{where}/state[time={step}]/position", coord, pos.tolist())
            for name, hi in (("orientation", 1e3), ("velocity", MAX_SPEED)):
                v = getattr(st, name, 0.0) or 0.0
                if not np.isfinite(float(v)) or abs(float(v)) > hi:
                    bad(f"{where}/state[time={step}]/{name}", f"a finite {name} within +-{hi:g}", v)


def _edge_barriers(lanes: list[Lane], shoulder_left: float = 1.0) -> list[Barrier]:
    """Concrete barrier beyond the left edge (+ shoulder) of every lane without a left
    neighbour (US-101: median barrier), cut where it would stand on another lane's surface
    (lanelets that touch without being linked as neighbours, e.g. slip roads)."""
    out = []
    for lane in lanes:
        if lane.left is not None or lg.length(lane.centerline) < 1.0:
            continue
        pts = lg.clean_polyline(lane.centerline)
        pts = lg.resample(pts, 2.0)
        w = lg.width_at(lane.centerline, lane.width, lg.arc_length(pts))
        line = lg.offset_polyline(pts, 0.5 * w + shoulder_left + 0.3)
        free = np.ones(len(line), bool)
        for other in lanes:
            if other.id == lane.id:
                continue
            s, d, _ = lg.project(other.centerline, line)
            inside = (s >= 0) & (s <= lg.length(other.centerline))
            half = 0.5 * lg.width_at(other.centerline, other.width, np.clip(s, 0, None))
            free &= ~(inside & (np.abs(d) < half + 3.0))  # 3 m: not in a gore next to a lane
        # keep runs of consecutive free points (at least 2)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], free.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a >= 2:
                out.append(Barrier("concrete", line[a:b], height=0.81))
    return out


def _pick_ego(tracks: dict[int, np.ndarray], info: dict, lanes: list[Lane], ego_id: int | None, path: Path,
              rank: int = 0) -> tuple[int, str]:
    if rank < 0:
        raise ConfigError(f"--ego-rank must be >= 0 (got {rank})")
    if ego_id is not None:
        if rank:
            raise UsageError("--ego and --ego-rank exclude each other")
        if ego_id not in tracks:
            raise UsageError(f"--ego {ego_id}: no such dynamic obstacle in {path.name}")
        if not np.isfinite(tracks[ego_id][:, 0]).all():
            raise UsageError(f"--ego {ego_id}: its track does not cover the whole recording")
        return ego_id, "chosen by the user (--ego)"
    by_id = {lane.id: lane for lane in lanes}
    keys = []
    for oid in sorted(tracks):
        arr = tracks[oid]
        if not np.isfinite(arr[:, 0]).all() or _obstacle_class(info[oid]) not in EGO_CLASSES:
            continue
        x, y, yaw, _ = arr[0]
        lane = by_id[_nearest_lane(lanes, np.array([x, y]), yaw)]
        middle = lane.left is not None and lane.right is not None
        ahead = 0
        for other, arr2 in tracks.items():
            if other == oid or not np.isfinite(arr2[0, 0]):
                continue
            dx, dy = arr2[0, 0] - x, arr2[0, 1] - y
            lon = dx * np.cos(yaw) + dy * np.sin(yaw)
            lat = -dx * np.sin(yaw) + dy * np.cos(yaw)
            ahead += int(0 < lon <= 50.0 and abs(lat) <= 5.5)
        keys.append((-ahead, not middle, oid))
    if not keys:
        raise FileFormatError(path, "$.dynamicObstacle", "a car whose track covers the whole recording (to be the ego)")
    if rank >= len(keys):
        raise UsageError(f"--ego-rank {rank}: {path.name} has only {len(keys)} car(s) that can be the ego")
    rule = ("car with a track over the whole recording and the most vehicles ahead (same/adjacent lane, "
            "within 50 m) in the first frame; middle lanes preferred; ties -> smallest id")
    if rank:
        rule += f"; rank {rank} in that order (--ego-rank {rank}: the first {rank} left out)"
    return sorted(keys)[rank][2], rule
