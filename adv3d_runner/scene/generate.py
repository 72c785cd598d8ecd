"""Highway scenario generator driven by the IDM/MOBIL traffic model.

One scene = a multi-lane highway (layout ``straight`` | ``curved`` | ``onramp`` | ``lanedrop``)
with traffic of a given density (``free`` .. ``congested``), simulated for a warm-up and then
recorded for 20 s at 10 Hz. The ego is one of the simulated vehicles (IDM/MOBIL too); its
trajectory is the logged ego track. Actor tracks are cut to the frames between their first and
last frame within ``KEEP_RADIUS`` (130 m) of the ego, and actors never that close are dropped
(a LiDAR with 120 m range cannot see them), which keeps files small.

Reproducibility: every random draw comes from ``numpy.random.default_rng(SeedSequence([split
tag, seed, attempt]))``. Splits have disjoint seed ranges *and* different namespaces
(``SPLITS``), so a training scene can never equal a benchmark scene, and the generator refuses
seeds outside the split's range. Same (split, seed, layout, density) -> identical file bytes.

Every scene is checked to have at least one vehicle ahead of the ego (same or adjacent lane,
within 50 m) during the first 5 s; if not, the scene is redrawn with ``attempt + 1`` (the
attempt number is stored in ``source.details``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..dynamics.traffic import IDMParams, MOBILParams, Traffic, equilibrium_speed
from ..geometry.angles import wrap_angle
from . import lanes as lg
from .schema import (Actor, Background, Barrier, Ego, Lane, Scene, Source, Track,
                     default_sensors, save_scene)

GENERATOR = "adv3d-highway-1"
LAYOUTS = ("straight", "curved", "onramp", "lanedrop")
# vehicles per km per lane at the start of the warm-up
DENSITIES = {"free": 10.0, "light": 18.0, "moderate": 28.0, "dense": 42.0, "congested": 65.0}
# split -> (namespace tag, first seed, end seed). Tags are arbitrary distinct constants.
SPLITS = {
    "benchmark": (0xBE4C, 0, 100_000),
    "train": (0x7A1D, 100_000, 1_000_000_000),
}
DT = 0.1
FRAMES = 200          # 20 s at 10 Hz
WARMUP_S = 8.0        # simulated before frame 0 so traffic is not in its initial pattern
# m: an actor's track keeps only the frames from its first to its last frame within this
# distance of the ego (the longest LiDAR range, 120 m of the HDL-64E, plus half a truck), so
# nothing a sensor on the ego could see is lost while files stay small.
KEEP_RADIUS = 100.0
AHEAD_RANGE = 50.0    # m, the "vehicle ahead" guarantee
AHEAD_SECONDS = 5.0
MAX_ATTEMPTS = 50

# class: (probability, (L, W, H) mean, (L, W, H) std, v0 factor, time headway T s)
CLASSES = {
    "sedan": (0.34, (4.75, 1.83, 1.45), (0.25, 0.05, 0.04), 1.0, 1.5),
    "hatchback": (0.10, (4.20, 1.78, 1.48), (0.20, 0.05, 0.04), 1.0, 1.5),
    "sports": (0.03, (4.50, 1.90, 1.28), (0.20, 0.05, 0.04), 1.08, 1.2),
    "suv": (0.22, (4.85, 1.95, 1.75), (0.25, 0.06, 0.06), 1.0, 1.5),
    "van": (0.07, (5.20, 2.00, 2.00), (0.30, 0.05, 0.10), 0.95, 1.6),
    "pickup": (0.11, (5.60, 2.02, 1.88), (0.30, 0.05, 0.06), 1.0, 1.5),
    "truck": (0.10, (14.5, 2.55, 3.90), (1.80, 0.03, 0.15), 0.82, 1.9),
    "bus": (0.03, (12.2, 2.55, 3.30), (0.40, 0.03, 0.10), 0.85, 1.8),
}
EGO_DIMENSIONS = (4.80, 1.90, 1.55)
EGO_WHEELBASE = 2.85


@dataclass(frozen=True)
class GeneratorProfile:
    """Traffic and road parameters of the generator; ``PROFILES["default"]`` is what the bundled
    benchmark was made with (its values are the module's historical constants, and the default
    profile draws exactly the random numbers it always drew, so the files stay byte-identical).

    Attributes:
        name: profile name (stored in ``source.details.profile`` unless default).
        density: vehicles per km per lane; None = the ``--density`` level (``DENSITIES``).
        lanes: main lanes drawn from ``[lo, hi)``.
        speed_limits: m/s, one drawn per scene.
        layouts: the layouts cycled by seed when ``--layout`` is not given.
        v0_mean, v0_std: desired speed = speed limit x class factor x N(v0_mean, v0_std).
        headway_scale, headway_sigma: desired time headway T = class T x headway_scale x
            exp(N(0, headway_sigma)) (no draw when headway_sigma is 0).
        idm, mobil: the traffic model's parameters.
    """

    name: str = "default"
    density: float | None = None
    lanes: tuple[int, int] = (2, 6)
    speed_limits: tuple[float, ...] = (26.8, 29.1, 31.3)  # 60 / 65 / 70 mph
    layouts: tuple[str, ...] = LAYOUTS
    v0_mean: float = 1.0
    v0_std: float = 0.07
    headway_scale: float = 1.0
    headway_sigma: float = 0.0
    idm: IDMParams = IDMParams()
    mobil: MOBILParams = MOBILParams()

    def desired_headway(self, rng: np.random.Generator, T: float) -> float:
        """A vehicle's T from its class T (draws only when ``headway_sigma`` > 0)."""
        if self.headway_sigma <= 0.0 and self.headway_scale == 1.0:
            return T
        noise = float(np.exp(rng.normal(0.0, self.headway_sigma))) if self.headway_sigma > 0.0 else 1.0
        return T * self.headway_scale * noise


#: ``us101``: fitted to the *train* recordings of ``scenes/real/`` (NGSIM US-101, 5 lanes, 65
#: mph, congested morning traffic) by ``bench/traffic.py --fit`` (random search minimising the
#: summed Kolmogorov-Smirnov distances of speed, time headway and lane changes per 5 s;
#: ``bench/results/traffic.json`` holds the search and the distances before and after).
PROFILES = {
    "default": GeneratorProfile(),
    # the fit's best candidate (bench/results/traffic.fit.json, "best"), rounded to 3 digits
    "us101": GeneratorProfile(name="us101", density=41.2, lanes=(5, 6), speed_limits=(29.1,),
                              layouts=("straight", "onramp"), v0_mean=0.783, v0_std=0.0555,
                              headway_scale=0.435, headway_sigma=0.0505,
                              idm=IDMParams(s0=2.94), mobil=MOBILParams(politeness=0.5, a_thr=0.0)),
}
PROFILE_TAG = {"us101": 0x5101}  # SeedSequence element of a non-default profile (own seed space)


def get_profile(profile: "str | GeneratorProfile | None") -> GeneratorProfile:
    """A profile by name (or the profile itself; None = default)."""
    if profile is None:
        return PROFILES["default"]
    if isinstance(profile, GeneratorProfile):
        return profile
    if profile not in PROFILES:
        raise ConfigError(f"unknown generator profile {profile!r}; choose one of {sorted(PROFILES)}")
    return PROFILES[profile]


@dataclass
class RoadLayout:
    """Road model in reference-line coordinates.

    ``ref`` (R, 2) reference polyline (centre of main lane 0). Lane k (0 = rightmost) has its
    centre at lateral offset ``offset(k, s)`` and width ``width(k, s)``; it exists on
    ``[start[k], end[k]]`` and allows lane changes from ``open[k]``.
    """

    ref: np.ndarray
    n_lanes: int
    lane_width: float
    start: np.ndarray
    end: np.ndarray
    open: np.ndarray
    kind: str
    ramp_lane: int | None = None       # index of the on-ramp lane
    drop_lane: int | None = None       # index of the dropped lane
    ramp_entry: float = 0.0            # m, where the ramp starts bending in
    taper: float = 80.0                # m, width taper before a lane end

    @property
    def length(self) -> float:
        return lg.length(self.ref)

    def offset(self, k: np.ndarray | int, s: np.ndarray) -> np.ndarray:
        """Lateral offset (m, left +) of lane k's centre at arc length s."""
        k = np.asarray(k)
        s = np.asarray(s, dtype=np.float64)
        base = (k - (1 if self.ramp_lane is not None else 0)) * self.lane_width
        if self.ramp_lane is None:
            return base + 0.0 * s
        # the ramp bends in from 30 m further right before its acceleration lane opens
        u = np.clip((s - self.ramp_entry) / max(self.open[self.ramp_lane] - self.ramp_entry, 1.0), 0.0, 1.0)
        bend = -30.0 * (0.5 + 0.5 * np.cos(np.pi * u))
        return base + np.where(k == self.ramp_lane, bend, 0.0)

    def width(self, k: int, s: np.ndarray) -> np.ndarray:
        """Lane width (m) at s, tapering to 0.3 m over the last ``taper`` m of an ending lane."""
        s = np.asarray(s, dtype=np.float64)
        w = np.full(s.shape, self.lane_width)
        if np.isfinite(self.end[k]):
            u = np.clip((self.end[k] - s) / self.taper, 0.0, 1.0)
            w = 0.3 + (self.lane_width - 0.3) * u
        return w

    def pose(self, k: np.ndarray, s: np.ndarray, d_extra: np.ndarray | float = 0.0) -> np.ndarray:
        """(..., 3) x, y, heading at lane k, arc length s, plus lateral ``d_extra``."""
        return lg.pose_at(self.ref, s, self.offset(k, s) + d_extra)


def _reference_line(rng: np.random.Generator, layout: str, total: float) -> np.ndarray:
    """Straight or gently curved (radius 500-2000 m, alternating) reference line, 5 m steps."""
    step = 5.0
    n = int(np.ceil(total / step)) + 1
    if layout != "curved":
        return np.stack([np.arange(n) * step, np.zeros(n)], axis=1)
    # curvature profile: straight / arc pieces of 150-400 m
    kappa = np.zeros(n)
    i = 0
    sign = rng.choice([-1.0, 1.0])
    while i < n:
        piece = int(rng.uniform(150, 400) / step)
        if rng.random() < 0.7:
            kappa[i:i + piece] = sign / rng.uniform(500.0, 2000.0)
            sign = -sign
        i += piece
    heading = np.concatenate([[0.0], np.cumsum(kappa[:-1] * step)])
    xy = np.concatenate([[[0.0, 0.0]], np.cumsum(step * np.stack([np.cos(heading[:-1]), np.sin(heading[:-1])], 1), axis=0)])
    return xy


def _make_layout(rng: np.random.Generator, layout: str, ego_s0: float, total: float,
                 lanes: tuple[int, int] = (2, 6)) -> RoadLayout:
    n_main = int(rng.integers(*lanes))  # default 2..5 main lanes
    width = float(rng.choice([3.5, 3.6, 3.7, 3.75]))
    ref = _reference_line(rng, layout, total)
    inf = np.inf
    if layout == "onramp":
        n = n_main + 1
        start = np.full(n, -inf)
        end = np.full(n, inf)
        open_ = np.full(n, -inf)
        s_open = ego_s0 + rng.uniform(40.0, 220.0)     # acceleration lane opens near the ego
        start[0] = s_open - 200.0
        open_[0] = s_open
        end[0] = s_open + rng.uniform(200.0, 320.0)
        return RoadLayout(ref, n, width, start, end, open_, layout, ramp_lane=0, ramp_entry=start[0])
    start = np.full(n_main, -inf)
    end = np.full(n_main, inf)
    open_ = np.full(n_main, -inf)
    if layout == "lanedrop":
        drop = 0 if rng.random() < 0.5 else n_main - 1
        if n_main == 2 and drop == 0:
            drop = 1
        end[drop] = ego_s0 + rng.uniform(250.0, 500.0)
        return RoadLayout(ref, n_main, width, start, end, open_, layout, drop_lane=drop)
    return RoadLayout(ref, n_main, width, start, end, open_, layout)


def _sample_vehicle(rng: np.random.Generator) -> tuple[str, np.ndarray, float, float]:
    names = list(CLASSES)
    probs = np.array([CLASSES[c][0] for c in names])
    cls = names[int(rng.choice(len(names), p=probs / probs.sum()))]
    _, mean, std, vf, T = CLASSES[cls]
    dims = np.maximum(np.array(mean) + rng.normal(0.0, 1.0, 3) * np.array(std), 0.5 * np.array(mean))
    return cls, dims, vf, T


@dataclass
class _Vehicle:
    cls: str
    dims: np.ndarray


def _populate(rng, road: RoadLayout, density: float, speed_limit: float, traffic: Traffic,
              vehicles: list, s_lo: float, s_hi: float, profile: GeneratorProfile = GeneratorProfile()) -> None:
    """Place vehicles in every lane between s_lo and s_hi with exponential-ish spacing."""
    spacing = 1000.0 / density
    for k in range(road.n_lanes):
        lo = max(s_lo, road.start[k] + 5.0)
        hi = min(s_hi, road.end[k] - road.taper)
        s = lo + rng.uniform(0.0, spacing)
        while s < hi:
            cls, dims, vf, T = _sample_vehicle(rng)
            gap = spacing * rng.uniform(0.6, 1.4)
            v0 = speed_limit * vf * rng.normal(profile.v0_mean, profile.v0_std)
            T = profile.desired_headway(rng, T)
            v = float(equilibrium_speed(np.array(max(gap - dims[0], 1.0)), np.array(v0), T=T,
                                        params=profile.idm))
            traffic.add(s, k, v, dims[0], v0, T)
            vehicles.append(_Vehicle(cls, dims))
            s += gap


def _inflow(rng, road: RoadLayout, density: float, speed_limit: float, traffic: Traffic, vehicles: list,
            profile: GeneratorProfile = GeneratorProfile()) -> None:
    """Keep traffic coming in at the start of the road (and of the ramp)."""
    spacing = 1000.0 / density
    for k in range(road.n_lanes):
        entry = 0.0 if not np.isfinite(road.start[k]) else road.start[k] + 5.0
        in_lane = traffic.active & (traffic.lane == k)
        last = traffic.s[in_lane].min() if in_lane.any() else np.inf
        if last - entry > spacing * rng.uniform(0.8, 1.6) and last - entry > 25.0:
            cls, dims, vf, T = _sample_vehicle(rng)
            v0 = speed_limit * vf * rng.normal(profile.v0_mean, profile.v0_std)
            T = profile.desired_headway(rng, T)
            v_last = traffic.v[in_lane][np.argmin(traffic.s[in_lane])] if in_lane.any() else v0
            traffic.add(entry, k, min(v0, v_last + 2.0), dims[0], v0, T)
            vehicles.append(_Vehicle(cls, dims))


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _simulate(rng, road: RoadLayout, density: float, speed_limit: float, ego_lane: int, ego_s0: float,
              profile: GeneratorProfile = GeneratorProfile()):
    """Run warm-up + recording. Returns per-frame arrays (F, N) and the vehicle list; the ego
    is index 0."""
    traffic = Traffic(road.start, road.end, road_end=road.length - 5.0, lane_open=road.open, idm=profile.idm,
                      mobil=profile.mobil)
    vehicles: list[_Vehicle] = []
    warm = int(round(WARMUP_S / DT))
    # the ego starts where it will be after the warm-up minus the distance driven meanwhile
    v_ego = speed_limit * 0.9
    ego_start = ego_s0 - v_ego * WARMUP_S
    traffic.add(ego_start, ego_lane, v_ego, EGO_DIMENSIONS[0], speed_limit * rng.normal(profile.v0_mean, 0.05),
                profile.desired_headway(rng, 1.5))
    vehicles.append(_Vehicle("sedan", np.array(EGO_DIMENSIONS)))
    _populate(rng, road, density, speed_limit, traffic, vehicles, 0.0, road.length - 50.0, profile)
    # remove vehicles overlapping the ego at the start
    ov = (traffic.lane == ego_lane) & (np.abs(traffic.s - ego_start) < 12.0)
    ov[0] = False
    traffic.active[ov] = False
    rec = {name: [] for name in ("s", "v", "lane", "lane_prev", "lc", "active")}
    for step in range(warm + FRAMES):
        if step >= warm:
            n = len(traffic.s)
            for name, arr in (("s", traffic.s), ("v", traffic.v), ("lane", traffic.lane),
                              ("lane_prev", traffic.lane_prev), ("lc", traffic.lc_progress),
                              ("active", traffic.active)):
                rec[name].append(arr.copy())
        traffic.step(DT)
        _inflow(rng, road, density, speed_limit, traffic, vehicles, profile)
        if not traffic.active[0]:
            break
    n = len(traffic.s)
    out = {}
    for name, rows in rec.items():
        fill = False if name == "active" else 0
        mat = np.full((FRAMES, n), fill, dtype=np.asarray(rows[0]).dtype if rows else float)
        for f, row in enumerate(rows):
            mat[f, : len(row)] = row
        out[name] = mat
    out["active"] = out["active"].astype(bool)
    return out, vehicles


def _poses(road: RoadLayout, rec: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, y, yaw (F, N) from road coordinates; yaw = lane heading + lateral drift angle."""
    s, v = rec["s"], rec["v"]
    w = _smoothstep(rec["lc"])
    d_from = road.offset(rec["lane_prev"], s)
    d_to = road.offset(rec["lane"], s)
    d = d_from + (d_to - d_from) * w
    xy = lg.point_at(road.ref, s)
    h = lg.heading_at(road.ref, s)
    normal = np.stack([-np.sin(h), np.cos(h)], axis=-1)
    pts = xy + d[..., None] * normal
    # drift angle from the change of lateral offset between frames (forward difference)
    dd = np.zeros_like(d)
    dd[:-1] = d[1:] - d[:-1]
    dd[-1] = dd[-2] if len(dd) > 1 else 0.0
    ds = np.maximum(v * DT, 1e-3)
    drift = np.arctan2(dd, ds)
    drift = np.where(v > 0.5, drift, 0.0)  # nearly stopped: keep the lane heading
    return pts[..., 0], pts[..., 1], wrap_angle(h + drift)


def _lanes_for_map(road: RoadLayout, speed_limit: float) -> list[Lane]:
    """Split lanes into sections at every lane start/end so neighbours are exact; ids are
    100 * section + lane index + 1."""
    cuts = {0.0, road.length}
    for k in range(road.n_lanes):
        for val in (road.start[k], road.open[k], road.end[k]):
            if np.isfinite(val) and 0.0 < val < road.length:
                cuts.add(float(val))
    cuts = sorted(cuts)
    sections = list(zip(cuts[:-1], cuts[1:]))

    def exists(k: int, a: float, b: float) -> bool:
        return road.start[k] <= a + 1e-6 and road.end[k] >= b - 1e-6

    def lane_id(sec: int, k: int) -> int:
        return 100 * sec + k + 1

    out: list[Lane] = []
    for sec, (a, b) in enumerate(sections):
        n_pts = max(2, int(np.ceil((b - a) / 10.0)) + 1)
        s = np.linspace(a, b, n_pts)
        for k in range(road.n_lanes):
            if not exists(k, a, b):
                continue
            pts = road.pose(k, s)[:, :2]
            opened = road.open[k] <= a + 1e-6
            left = k + 1 if k + 1 < road.n_lanes and exists(k + 1, a, b) and opened and road.open[k + 1] <= a + 1e-6 else None
            right = k - 1 if k - 1 >= 0 and exists(k - 1, a, b) and opened and road.open[k - 1] <= a + 1e-6 else None
            succ = [lane_id(sec + 1, k)] if sec + 1 < len(sections) and exists(k, *sections[sec + 1]) else []
            out.append(Lane(
                id=lane_id(sec, k), centerline=pts, width=road.width(k, s),
                left=None if left is None else lane_id(sec, left),
                right=None if right is None else lane_id(sec, right),
                successors=succ, speed_limit=speed_limit,
            ))
    return out


def _barriers(rng, road: RoadLayout, shoulder_left: float, shoulder_right: float) -> list[Barrier]:
    """Concrete median barrier on the left edge; a guardrail on the right (70 % of scenes).
    With an on-ramp the right guardrail runs along the main road up to the gore (where the
    ramp comes within its shoulder of the main road), and a second one along the ramp's outer
    edge, so no barrier ever crosses a lane."""
    s = np.linspace(0.0, road.length, max(2, int(road.length / 10.0) + 1))
    ks = np.arange(road.n_lanes)
    exists = (s[None, :] >= road.start[:, None]) & (s[None, :] <= road.end[:, None])
    offs = np.stack([road.offset(k, s) for k in ks])
    wid = np.stack([road.width(k, s) for k in ks])
    left_edge = np.max(np.where(exists, offs + wid / 2, -np.inf), axis=0) + shoulder_left + 0.3
    out = [Barrier("concrete", lg.pose_at(road.ref, s, left_edge)[:, :2], height=0.81)]
    if rng.random() >= 0.7:
        return out
    if road.ramp_lane is None:
        right_edge = np.min(np.where(exists, offs - wid / 2, np.inf), axis=0) - shoulder_right - 0.3
        out.append(Barrier("guardrail", lg.pose_at(road.ref, s, right_edge)[:, :2], height=0.75))
        return out
    r = road.ramp_lane
    main = np.ones(road.n_lanes, bool)
    main[r] = False
    main_edge = np.min(np.where(exists[main], (offs - wid / 2)[main], np.inf), axis=0) - shoulder_right - 0.3
    ramp_inner = offs[r] + wid[r] / 2
    gore = exists[r] & (ramp_inner > main_edge - 1.0)
    nose = s[np.argmax(gore)] if gore.any() else road.length
    before = s < nose
    if before.sum() >= 2:
        out.append(Barrier("guardrail", lg.pose_at(road.ref, s[before], main_edge[before])[:, :2], height=0.75))
    after = s >= road.start[r]
    outer = np.where(exists[r], offs[r] - wid[r] / 2, main_edge + shoulder_right + 0.3) - shoulder_right - 0.3
    outer = np.minimum(outer, main_edge)
    if after.sum() >= 2:
        out.append(Barrier("guardrail", lg.pose_at(road.ref, s[after], outer[after])[:, :2], height=0.75))
    return out


def _track_from(x, y, yaw, v, active) -> Track | None:
    frames = np.flatnonzero(active)
    if len(frames) == 0:
        return None
    a, b = frames[0], frames[-1] + 1
    valid = active[a:b]
    return Track(x=x[a:b], y=y[a:b], yaw=yaw[a:b], speed=v[a:b], start=int(a),
                 valid=None if valid.all() else valid)


def vehicles_ahead(scene: Scene, seconds: float = AHEAD_SECONDS, max_range: float = AHEAD_RANGE,
                   lateral: float | None = None) -> list[int]:
    """Ids of actors ahead of the ego (0 < longitudinal distance <= ``max_range`` m, in the
    ego's lane or an adjacent one: |lateral| <= 1.5 lane widths) in some frame of the first
    ``seconds`` s."""
    n = min(scene.frames, int(round(seconds / scene.dt)) + 1)
    ego = scene.ego_poses()[:n]
    if lateral is None:
        widths = [float(np.median(lane.width)) for lane in scene.lanes]
        lateral = 1.5 * (np.median(widths) if widths else 3.7)
    poses, valid = scene.all_actor_poses()
    if len(scene.actors) == 0:
        return []
    rel = poses[:, :n, :2] - ego[None, :, :2]
    c, s = np.cos(ego[:, 2]), np.sin(ego[:, 2])
    lon = rel[..., 0] * c + rel[..., 1] * s
    lat = -rel[..., 0] * s + rel[..., 1] * c
    with np.errstate(invalid="ignore"):
        hit = valid[:, :n] & (lon > 0) & (lon <= max_range) & (np.abs(lat) <= lateral)
    return [scene.actors[i].id for i in np.flatnonzero(hit.any(axis=1))]


def check_split(split: str, seed: int) -> None:
    """Raise ConfigError unless ``seed`` lies in the split's reserved range."""
    if split not in SPLITS:
        raise ConfigError(f"unknown split {split!r}; choose one of {sorted(SPLITS)}")
    _, lo, hi = SPLITS[split]
    if not lo <= seed < hi:
        raise ConfigError(f"seed {seed} is outside the {split!r} split's reserved range [{lo}, {hi}); "
                          "benchmark and training scenes must not overlap")


def default_layout_density(seed: int, profile: GeneratorProfile | None = None) -> tuple[str, str]:
    """The mix used when layout/density are not given: cycles through every combination (of the
    profile's layouts; a profile with its own density has no density levels to cycle)."""
    dens = list(DENSITIES)
    layouts = LAYOUTS if profile is None else profile.layouts
    return layouts[seed % len(layouts)], dens[(seed // len(layouts)) % len(dens)]


def _profile_tag(profile: GeneratorProfile) -> int:
    import zlib

    return PROFILE_TAG.get(profile.name, zlib.crc32(profile.name.encode()))


def generate_scene(seed: int, split: str = "benchmark", layout: str | None = None, density: str | None = None,
                   profile: "str | GeneratorProfile | None" = None) -> Scene:
    """Generate one highway scene (deterministic in its arguments).

    Args:
        seed: scene seed, inside the split's reserved range (``SPLITS``).
        split: ``benchmark`` or ``train``.
        layout: one of ``LAYOUTS``; None picks by seed (``default_layout_density``).
        density: one of ``DENSITIES``; None picks by seed. Not with a profile that sets its own
            density (``us101``).
        profile: a name of ``PROFILES`` or a :class:`GeneratorProfile` (None: ``default``, what
            the bundled benchmark was made with). A non-default profile draws from its own
            seed space (an extra ``SeedSequence`` element) and names its scenes
            ``highway-<profile>-<split>-<seed>``.
    """
    check_split(split, seed)
    prof = get_profile(profile)
    default = prof.name == "default"
    d_layout, d_density = default_layout_density(seed, None if default else prof)
    layout = layout or d_layout
    if prof.density is not None and density is not None:
        raise ConfigError(f"profile {prof.name!r} sets its own density ({prof.density:g} vehicles/km/lane); "
                          "leave out --density")
    density = density or d_density
    if layout not in LAYOUTS:
        raise ConfigError(f"unknown layout {layout!r}; choose one of {list(LAYOUTS)}")
    if density not in DENSITIES:
        raise ConfigError(f"unknown density {density!r}; choose one of {list(DENSITIES)}")
    tag = SPLITS[split][0]
    for attempt in range(MAX_ATTEMPTS):
        entropy = [tag, seed, attempt, LAYOUTS.index(layout), list(DENSITIES).index(density)]
        if not default:
            entropy.append(_profile_tag(prof))
        rng = np.random.default_rng(np.random.SeedSequence(entropy))
        scene = _generate_once(rng, seed, split, layout, density, attempt, prof)
        if scene is not None and vehicles_ahead(scene):
            return scene
    raise ConfigError(f"could not generate a scene with a vehicle ahead for seed {seed} in {MAX_ATTEMPTS} attempts")


def _generate_once(rng, seed: int, split: str, layout: str, density: str, attempt: int,
                   profile: GeneratorProfile = GeneratorProfile()) -> Scene | None:
    speed_limit = float(rng.choice(list(profile.speed_limits)))
    ego_s0 = 300.0
    total = ego_s0 + FRAMES * DT * speed_limit * 1.3 + 300.0
    road = _make_layout(rng, layout, ego_s0, total, profile.lanes)
    main = [k for k in range(road.n_lanes) if k != road.ramp_lane and k != road.drop_lane]
    ego_lane = int(rng.choice(main))
    per_km = DENSITIES[density] if profile.density is None else profile.density
    rec, vehicles = _simulate(rng, road, per_km, speed_limit, ego_lane, ego_s0, profile)
    if not rec["active"][:, 0].all():
        return None  # the ego left the road (should not happen with the margins above)
    x, y, yaw = _poses(road, rec)
    v = rec["v"]
    ego = Ego(dimensions=EGO_DIMENSIONS, wheelbase=EGO_WHEELBASE,
              track=Track(x=x[:, 0], y=y[:, 0], yaw=yaw[:, 0], speed=v[:, 0]), sensors=default_sensors())
    actors: list[Actor] = []
    dist = np.hypot(x - x[:, :1], y - y[:, :1])
    near = (rec["active"] & (dist <= KEEP_RADIUS)).any(axis=0)
    for i in np.flatnonzero(near)[1:] if near[0] else np.flatnonzero(near):
        if i == 0:
            continue
        close = rec["active"][:, i] & (dist[:, i] <= KEEP_RADIUS)
        f = np.flatnonzero(close)
        span = np.zeros(FRAMES, bool)
        span[f[0]:f[-1] + 1] = True
        track = _track_from(x[:, i], y[:, i], yaw[:, i], v[:, i], rec["active"][:, i] & span)
        if track is None:
            continue
        actors.append(Actor(id=len(actors) + 1, cls=vehicles[i].cls, dimensions=vehicles[i].dims, track=track))
    shoulder_left = float(rng.uniform(0.6, 3.0))
    shoulder_right = float(rng.uniform(2.4, 3.2))
    background = Background(shoulder_left=shoulder_left, shoulder_right=shoulder_right, ground_margin=30.0,
                            lane_markings=True, barriers=_barriers(rng, road, shoulder_left, shoulder_right))
    details = {
        "generator": GENERATOR, "split": split, "seed": int(seed), "attempt": attempt,
        "layout": layout, "density": density, "lanes": int(road.n_lanes), "speed_limit": speed_limit,
        "command": f"adv3d scenes generate --split {split} --seed {seed} --count 1 --layout {layout} --density {density}",
    }
    scene_id = f"highway-{split}-{seed:06d}"
    if profile.name != "default":  # the default profile's files stay as they were
        details["profile"] = profile.name
        if profile.density is not None:
            details["density"] = f"{profile.density:g} vehicles/km/lane ({profile.name})"
        details["command"] = (f"adv3d scenes generate --split {split} --seed {seed} --count 1 --layout {layout} "
                              f"--profile {profile.name}")
        scene_id = f"highway-{profile.name}-{split}-{seed:06d}"
    source = Source(kind="generated", details=details, licence="CC0-1.0 (synthetic, generated by adv3d)",
                    attribution=None)
    scene = Scene(id=scene_id, source=source, dt=DT, frames=FRAMES,
                  lanes=_lanes_for_map(road, speed_limit), background=background, ego=ego, actors=actors)
    return scene


def generate_scenes(out_dir: str | Path, count: int, seed: int, split: str = "benchmark",
                    layout: str | None = None, density: str | None = None, progress_desc: str = "scenes",
                    profile: str | None = None, library=None) -> list[Path]:
    """Generate ``count`` scenes with seeds ``seed .. seed + count - 1`` into ``out_dir``
    (``<scene id>.json.gz``). Refuses to write training scenes, or scenes of another profile
    than the default, into the benchmark folder.

    With a vehicle ``library``, every actor records the asset drawn for it
    (``actors.assign_assets``), so the scene keeps its meshes whatever the library becomes."""
    from ..progress import progress
    out_dir = Path(out_dir)
    check_split(split, seed)
    check_split(split, seed + count - 1)
    prof = get_profile(profile)
    if (split != "benchmark" or prof.name != "default") and (out_dir.resolve() / "x").is_relative_to(_benchmark_dir()):
        what = f"{split!r}" if split != "benchmark" else f"profile {prof.name!r}"
        raise ConfigError(f"refusing to write {what} scenes into the benchmark folder {out_dir}")
    paths = []
    for s in progress(range(seed, seed + count), desc=progress_desc, total=count, unit="scene"):
        scene = generate_scene(s, split, layout, density, prof)
        if library is not None:
            from .actors import assign_assets

            scene = assign_assets(scene, library)
        path = out_dir / f"{scene.id}.json.gz"
        save_scene(scene, path)
        paths.append(path)
    return paths


def _benchmark_dir() -> Path:
    from ..fileio import REPO_ROOT
    return (REPO_ROOT / "scenes" / "highway").resolve()
