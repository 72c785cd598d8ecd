"""Implicit occupancy-and-flow model of Autonomy-B (after ImplicitO, Agro et al., CVPR 2023).

One network replaces Autonomy-A's detector, tracker and predictor: it is queried at arbitrary
BEV points q = (x, y, t) in the **ego frame of the current frame** at times t in [0, horizon]
s and returns the probability that q is occupied by a vehicle and the BEV backward flow
(m/s, :mod:`adv3d_runner.metrics.occupancy`) of whatever occupies it.

Pipeline:

1. **Input**: the LiDAR sweeps of the current frame and of ``sweep_lags`` frames before it
   (0.5 s and 1 s by default), each voxelised with the detector's BEV voxeliser
   (:func:`adv3d_runner.autonomy.detector.voxelize`: height-slice occupancies + a point-density
   channel per sweep) and stacked as channels (:func:`bev_input`). With ``sweep_frame="ego"``
   (the default) each sweep stays in its own ego frame, i.e. in a frame that moves with the
   ego: a car as fast as the ego lies on itself in every sweep, one 2 m/s faster is 2 m further
   ahead in the current sweep than in the 1 s old one (relative motion is a few cells, which
   the encoder sees); the road-side moves backwards. With ``sweep_frame="map"`` the sweeps are
   moved into the current ego frame (ego motion compensated, as ImplicitO does): then a car at
   30 m/s leaves its 1 s old points 30 m behind it, beyond what this small encoder relates,
   and models trained that way (with 0.2 s / 0.4 s or 0.5 s / 1 s lags) predicted every flow
   close to the ego's own speed. A sweep that does not exist yet (the first frames of an episode) is all
   zeros; training drops sweeps the same way, so the model knows what that means.
2. **Encoder**: a small BEV CNN (the detector's conv blocks; strides 2, 4, 8, merged top-down
   back to stride 2) gives a feature map Z at ``2 x resolution`` m per cell.
3. **Implicit decoder** per query point: Z is sampled bilinearly at a *reference point* that
   moves with the ego's current speed v, (x - v t, y) (on a highway most traffic moves about as
   fast as the ego, so the reference lands near where the occupant is now); a small MLP predicts
   ``offsets`` more sampling points from that feature (ImplicitO's learned offsets, here
   concatenated instead of attended over), and a second MLP maps the features, the offsets and
   the query's position, time and the ego's speed to an occupancy logit and a flow, predicted as
   a residual to (v, 0).

Weights ship as a tensor-only ``state_dict`` (``occupancy.pt``, read with
``torch.load(weights_only=True)``: no pickle) next to ``config.json`` in
``assets/models/occupancy/``; ``adv3d train occupancy`` makes them.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError
from ..fileio import REPO_ROOT
from .detector import DetectorConfig, _conv, voxelize

DEFAULT_MODEL_DIR = REPO_ROOT / "assets" / "models" / "occupancy"
WEIGHTS_NAME = "occupancy.pt"
CONFIG_NAME = "config.json"
CONFIG_FORMAT = "adv3d-occupancy-config"
CONFIG_VERSION = 1
_OFFSET_SCALE = 10.0  # m: the offset MLP's outputs are offsets / this
_FLOW_SCALE = 5.0     # m/s: the flow output is (v, 0) + this x the network's residual


@dataclass
class OccupancyConfig:
    """Input grid, architecture and query range (stored in ``config.json``).

    Attributes:
        resolution: BEV input cell, m (feature cells are twice this).
        x_range, y_range: input grid in the current ego frame, m (the far ends are extended so
            the cell counts are multiples of 8).
        z_edges: height slice edges above the ground, m.
        sweep_lags: frames before the current one whose sweeps are stacked (0 = current).
        sweep_frame: "ego" (each sweep in its own ego frame: moving with the ego) or "map"
            (moved into the current ego frame: ego motion compensated).
        channels: encoder stage widths (strides 2, 4, 8). features: width of Z.
        offsets: learned sampling offsets per query. hidden: decoder MLP width.
        horizon: s, queries cover t in [0, horizon] (the planner's horizon).
        dt: s between frames (sweep lags are in frames).
    """

    resolution: float = 0.5
    x_range: tuple[float, float] = (-24.0, 72.0)
    y_range: tuple[float, float] = (-24.0, 24.0)
    z_edges: tuple[float, ...] = (0.3, 0.8, 1.3, 1.8, 4.5)
    sweep_lags: tuple[int, ...] = (0, 5, 10)
    sweep_frame: str = "ego"
    channels: tuple[int, int, int] = (16, 32, 64)
    features: int = 32
    offsets: int = 2
    hidden: int = 64
    horizon: float = 5.0
    dt: float = 0.1

    def __post_init__(self) -> None:
        self.x_range = tuple(float(v) for v in self.x_range)
        self.y_range = tuple(float(v) for v in self.y_range)
        self.z_edges = tuple(float(v) for v in self.z_edges)
        self.sweep_lags = tuple(int(v) for v in self.sweep_lags)
        self.channels = tuple(int(v) for v in self.channels)
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ConfigError(f"occupancy resolution must be > 0 m, got {self.resolution}")
        if not self.sweep_lags or self.sweep_lags[0] != 0 or any(b <= a for a, b in zip(self.sweep_lags, self.sweep_lags[1:])):
            raise ConfigError(f"sweep_lags must start at 0 and increase, got {self.sweep_lags}")
        if len(self.channels) != 3 or self.offsets < 0 or self.features < 1 or self.hidden < 1:
            raise ConfigError("channels must have 3 entries; offsets >= 0, features and hidden >= 1")
        if not self.horizon > 0:
            raise ConfigError(f"horizon must be > 0 s, got {self.horizon}")
        if self.sweep_frame not in ("ego", "map"):
            raise ConfigError(f"sweep_frame must be 'ego' or 'map', got {self.sweep_frame!r}")

    @property
    def voxel_grid(self) -> DetectorConfig:
        """The grid in the detector's terms (so :func:`~.detector.voxelize` serves both)."""
        return DetectorConfig(resolution=self.resolution, x_range=self.x_range, y_range=self.y_range,
                              z_edges=self.z_edges)

    @property
    def grid_shape(self) -> tuple[int, int]:
        return self.voxel_grid.grid_shape

    @property
    def channels_per_sweep(self) -> int:
        return len(self.z_edges)  # nz slices + density

    @property
    def in_channels(self) -> int:
        return len(self.sweep_lags) * self.channels_per_sweep

    @property
    def feature_cell(self) -> float:
        return 2.0 * self.resolution

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: "dict | Node", path: str | Path | None = None) -> "OccupancyConfig":
        """Build from the ``occupancy`` object of a model's config.json: every field typed and
        bounded (unknown keys refused), the input grid at most the detector's
        ``MAX_GRID_CELLS`` cells."""
        from ..validate import Node
        from .detector import build_grid_config, grid_params

        node = d if isinstance(d, Node) else Node(d, "$.occupancy", path)
        node.object("an object of occupancy model parameters")
        node.check_keys(cls.__dataclass_fields__)
        dflt = cls()
        g = node.get
        kw: dict[str, Any] = {
            **grid_params(node, dflt),
            "sweep_lags": tuple(c.integer(lo=0, hi=1000) for c in g("sweep_lags", list(dflt.sweep_lags)).items(non_empty=True)),
            "sweep_frame": g("sweep_frame", dflt.sweep_frame).string(choices=("ego", "map")),
            "channels": tuple(c.integer(lo=1, hi=4096) for c in g("channels", list(dflt.channels)).items(length=3)),
            "features": g("features", dflt.features).integer(lo=1, hi=4096),
            "offsets": g("offsets", dflt.offsets).integer(lo=0, hi=64),
            "hidden": g("hidden", dflt.hidden).integer(lo=1, hi=4096),
            "horizon": g("horizon", dflt.horizon).number(lo=0.0, hi=60.0, lo_open=True),
            "dt": g("dt", dflt.dt).number(lo=1e-3, hi=10.0),
        }
        return build_grid_config(cls, node, kw, "occupancy model parameters")


# ----------------------------------------------------------------------------- numpy parts

def to_current_frame(points: np.ndarray, pose: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Points (P, 3+) in the ego frame of ``pose`` -> the ego frame of ``current`` (both map-frame
    poses x, y, yaw); z and extra columns are kept."""
    p = np.asarray(points)
    if p.size == 0 or np.array_equal(pose, current):
        return p
    x0, y0, a0 = (float(v) for v in pose)
    x1, y1, a1 = (float(v) for v in current)
    d = a0 - a1
    c, s = math.cos(d), math.sin(d)
    # translation of pose's origin seen from current
    cx, cy = math.cos(a1), math.sin(a1)
    tx = cx * (x0 - x1) + cy * (y0 - y1)
    ty = -cy * (x0 - x1) + cx * (y0 - y1)
    out = p.copy()
    out[:, 0] = c * p[:, 0] - s * p[:, 1] + tx
    out[:, 1] = s * p[:, 0] + c * p[:, 1] + ty
    return out


def keep_points(points: np.ndarray, cfg: OccupancyConfig, margin: float = 40.0) -> np.ndarray:
    """The points a sweep contributes: above the first height edge and below the last, within
    ``margin`` m of the grid (they move into the grid of later frames); float32 (P, 3)."""
    p = np.asarray(points)
    if p.size == 0:
        return np.zeros((0, 3), np.float32)
    p = p.reshape(len(p), -1)
    ok = (p[:, 2] >= cfg.z_edges[0]) & (p[:, 2] < cfg.z_edges[-1])
    ok &= (p[:, 0] >= cfg.x_range[0] - margin) & (p[:, 0] <= cfg.x_range[1] + margin)
    ok &= (p[:, 1] >= cfg.y_range[0] - margin) & (p[:, 1] <= cfg.y_range[1] + margin)
    return np.ascontiguousarray(p[ok, :3], dtype=np.float32)


def bev_input(sweeps: Sequence[tuple[np.ndarray, np.ndarray] | None], current: np.ndarray,
              cfg: OccupancyConfig) -> np.ndarray:
    """The network input of one frame.

    Args:
        sweeps: one entry per ``cfg.sweep_lags``: (points (P, 3+) in that sweep's ego frame,
            that ego pose (3,) in the map frame), or None for a sweep that does not exist.
        current: the current ego pose (3,).
    Returns:
        (len(sweep_lags) x len(z_edges), nx, ny) float32: per sweep the detector's voxel
        channels (:func:`~.detector.voxelize`), in the sweep's own ego frame
        (``cfg.sweep_frame == "ego"``) or moved into the current one (``"map"``); zeros for a
        missing sweep.
    """
    if len(sweeps) != len(cfg.sweep_lags):
        raise ValueError(f"{len(sweeps)} sweeps for {len(cfg.sweep_lags)} lags")
    grid = cfg.voxel_grid
    nx, ny = grid.grid_shape
    per = cfg.channels_per_sweep
    out = np.zeros((len(sweeps) * per, nx, ny), np.float32)
    for i, sw in enumerate(sweeps):
        if sw is None:
            continue
        pts, pose = sw
        if cfg.sweep_frame == "map":
            pts = to_current_frame(pts, np.asarray(pose, float), np.asarray(current, float))
        out[i * per:(i + 1) * per] = voxelize(pts, grid)
    return out


# ----------------------------------------------------------------------------- network

class OccupancyNet(nn.Module):
    """BEV encoder + implicit decoder (see module docstring).

    ``encode(x (B, C, nx, ny)) -> Z (B, F, nx/2, ny/2)``;
    ``decode(Z, queries (B, Q, 3) ego-frame x, y (m), t (s), speed (B,) m/s)``
    -> occupancy logits (B, Q), flow (B, Q, 2) m/s in the ego frame.
    """

    def __init__(self, cfg: OccupancyConfig):
        super().__init__()
        c1, c2, c3 = cfg.channels
        f = cfg.features
        self.cfg = cfg
        self.stage1 = nn.Sequential(_conv(cfg.in_channels, c1, 2), _conv(c1, c1))           # /2
        self.stage2 = nn.Sequential(_conv(c1, c2, 2), _conv(c2, c2), _conv(c2, c2))          # /4
        self.stage3 = nn.Sequential(_conv(c2, c3, 2), _conv(c3, c3), _conv(c3, c3))          # /8
        self.merge4 = nn.Sequential(nn.Conv2d(c3 + c2, f, 1, bias=False), nn.BatchNorm2d(f), nn.ReLU(inplace=True),
                                    _conv(f, f))
        self.merge2 = nn.Sequential(nn.Conv2d(f + c1, f, 1), nn.ReLU(inplace=True))
        n_pos = 5
        k = cfg.offsets
        self.offset_mlp = nn.Sequential(nn.Linear(f + n_pos, cfg.hidden // 2), nn.ReLU(inplace=True),
                                        nn.Linear(cfg.hidden // 2, 2 * k)) if k else None
        if self.offset_mlp is not None:
            nn.init.normal_(self.offset_mlp[-1].weight, std=1e-3)
            nn.init.zeros_(self.offset_mlp[-1].bias)
        self.head = nn.Sequential(nn.Linear(f * (1 + k) + n_pos + 2 * k, cfg.hidden), nn.ReLU(inplace=True),
                                  nn.Linear(cfg.hidden, cfg.hidden), nn.ReLU(inplace=True),
                                  nn.Linear(cfg.hidden, 3))
        nn.init.constant_(self.head[-1].bias, 0.0)
        with torch.no_grad():
            self.head[-1].bias[0] = -3.0  # prior ~5 % occupied: a stable start
        nx, ny = cfg.grid_shape
        cell = cfg.feature_cell
        # grid_sample's normalised coordinates of a point: u = a * coord + b (align_corners=False)
        self.register_buffer("_ax", torch.tensor(2.0 / ((nx // 2) * cell)), persistent=False)
        self.register_buffer("_ay", torch.tensor(2.0 / ((ny // 2) * cell)), persistent=False)
        self._bx = -1.0 - 2.0 * cfg.x_range[0] / ((nx // 2) * cell)
        self._by = -1.0 - 2.0 * cfg.y_range[0] / ((ny // 2) * cell)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        f1 = self.stage1(x)
        f2 = self.stage2(f1)
        f3 = self.stage3(f2)
        up = nn.functional.interpolate(f3, size=f2.shape[-2:], mode="nearest")
        f4 = self.merge4(torch.cat([up, f2], dim=1))
        up2 = nn.functional.interpolate(f4, size=f1.shape[-2:], mode="nearest")
        return self.merge2(torch.cat([up2, f1], dim=1))

    def _sample(self, z: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Bilinear features (B, Q, F) of Z at ego-frame points x, y (B, Q) (zeros outside)."""
        # Z is (B, F, X, Y): grid_sample's "width" axis is y, its "height" axis is x
        grid = torch.stack([y * self._ay + self._by, x * self._ax + self._bx], dim=-1)[:, :, None]  # (B, Q, 1, 2)
        s = nn.functional.grid_sample(z, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        return s[..., 0].transpose(1, 2)

    def decode(self, z: torch.Tensor, queries: torch.Tensor, speed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x, y, t = queries[..., 0], queries[..., 1], queries[..., 2]
        v = speed[:, None].expand_as(x)
        xr = x - v * t
        pos = torch.stack([xr / 50.0, y / 25.0, t / 5.0, v / 30.0, x / 100.0], dim=-1)
        z0 = self._sample(z, xr, y)
        feats = [z0]
        offs = []
        if self.offset_mlp is not None:
            off = self.offset_mlp(torch.cat([z0, pos], dim=-1)) * _OFFSET_SCALE  # (B, Q, 2K)
            for k in range(self.cfg.offsets):
                feats.append(self._sample(z, xr + off[..., 2 * k], y + off[..., 2 * k + 1]))
            offs = [off / _OFFSET_SCALE]
        out = self.head(torch.cat(feats + [pos] + offs, dim=-1))
        flow = out[..., 1:3] * _FLOW_SCALE
        flow = flow + torch.stack([v, torch.zeros_like(v)], dim=-1)
        return out[..., 0], flow

    def forward(self, x: torch.Tensor, queries: torch.Tensor, speed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.decode(self.encode(x), queries, speed)


# ----------------------------------------------------------------------------- runtime

class ImplicitField:
    """The model's occupancy and flow of one frame, queried lazily (the
    :class:`~adv3d_runner.autonomy.interface.OccupancyField` of Autonomy-B's outputs).

    Attributes:
        pose: (3,) the frame's ego pose (map frame); speed: its speed, m/s; horizon: s.
    """

    def __init__(self, model: "OccupancyModel", z: torch.Tensor, pose: np.ndarray, speed: float):
        self._model = model
        self._z = z
        self.pose = np.asarray(pose, dtype=np.float64).reshape(3)
        self.speed = float(speed)
        self.horizon = float(model.cfg.horizon)

    def query_local(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame queries (Q, 3) x, y (m), t (s) -> occupancy probability (Q,) float64 and
        flow (Q, 2) m/s in the ego frame."""
        q = np.asarray(queries, dtype=np.float32).reshape(-1, 3)
        if len(q) == 0:
            return np.zeros(0), np.zeros((0, 2))
        m = self._model
        t0 = m.clock()
        with torch.inference_mode():
            logit, flow = m.net.decode(self._z, torch.from_numpy(np.ascontiguousarray(q))[None],
                                       torch.tensor([self.speed], dtype=torch.float32))
            occ = torch.sigmoid(logit[0]).numpy().astype(np.float64)
            fl = flow[0].numpy().astype(np.float64)
        m.timings["decode"] = m.timings.get("decode", 0.0) + (m.clock() - t0)
        m.timings["queries"] = m.timings.get("queries", 0) + len(q)
        return occ, fl

    def query(self, xy: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame points xy (Q, 2) at times t (Q,) s after the frame -> occupancy probability
        (Q,) and flow (Q, 2) m/s in the map frame."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        tt = np.broadcast_to(np.asarray(t, dtype=np.float64), (len(p),))
        x0, y0, a = self.pose
        c, s = math.cos(a), math.sin(a)
        dx, dy = p[:, 0] - x0, p[:, 1] - y0
        occ, fl = self.query_local(np.stack([c * dx + s * dy, -s * dx + c * dy, tt], axis=1))
        return occ, np.stack([c * fl[:, 0] - s * fl[:, 1], s * fl[:, 0] + c * fl[:, 1]], axis=1)


class OccupancyModel:
    """The trained network behind Autonomy-B: :meth:`encode` one frame, query the
    :class:`ImplicitField` it returns.

    Args:
        cfg: its config. net: an :class:`OccupancyNet` (random weights when None).
        threads: torch intra-op threads (1: the episode loop is single-core).

    ``timings`` holds seconds of the last frame: ``input`` (voxelising the sweeps), ``encode``,
    and ``decode`` (summed over the frame's queries, with ``queries`` their number); measured
    with ``clock`` (benchmarks on a shared machine set ``time.thread_time``).
    """

    clock = staticmethod(time.perf_counter)

    def __init__(self, cfg: OccupancyConfig | None = None, net: OccupancyNet | None = None, threads: int | None = 1):
        self.cfg = cfg or OccupancyConfig()
        self.net = (net or OccupancyNet(self.cfg)).eval()
        self.threads = threads
        self.timings: dict[str, float] = {}

    def encode(self, sweeps: Sequence[tuple[np.ndarray, np.ndarray] | None], pose: np.ndarray,
               speed: float) -> ImplicitField:
        """The field of one frame from its sweeps (see :func:`bev_input`), ego pose and speed."""
        if self.threads is not None and torch.get_num_threads() != self.threads:
            torch.set_num_threads(self.threads)
        t0 = self.clock()
        grid = bev_input(sweeps, pose, self.cfg)
        t1 = self.clock()
        with torch.inference_mode():
            z = self.net.encode(torch.from_numpy(grid)[None])
        self.timings = {"input": t1 - t0, "encode": self.clock() - t1, "decode": 0.0, "queries": 0}
        return ImplicitField(self, z, pose, speed)


def save_occupancy(model: OccupancyModel, out_dir: str | Path, extra_config: dict[str, Any] | None = None) -> Path:
    """Write ``occupancy.pt`` (float32 tensor state_dict) and ``config.json`` into ``out_dir``."""
    import io

    from ..fileio import atomic_write_bytes, write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu().contiguous() for k, v in model.net.state_dict().items()}, buf)
    atomic_write_bytes(out / WEIGHTS_NAME, buf.getvalue())
    doc = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, "weights": WEIGHTS_NAME, "occupancy": model.cfg.to_dict()}
    doc.update(extra_config or {})
    write_json(out / CONFIG_NAME, doc)
    return out / WEIGHTS_NAME


def load_occupancy(path: str | Path = DEFAULT_MODEL_DIR, threads: int | None = 1) -> OccupancyModel:
    """Load a trained occupancy model from its folder (or its ``config.json``).

    Raises:
        FileFormatError: missing/invalid config, or weights that are not a plain tensor
            state_dict matching the config (``torch.load(weights_only=True)`` refuses pickles).
    """
    from .detector import load_state_into, read_model_config

    cfg_path, doc = read_model_config(path, CONFIG_NAME, CONFIG_FORMAT, CONFIG_VERSION,
                                      "an occupancy config.json (train one with `adv3d train occupancy`)")
    cfg = OccupancyConfig.from_dict(doc["occupancy"])
    net = OccupancyNet(cfg)
    load_state_into(net, doc, cfg_path, WEIGHTS_NAME, "occupancy weights (state_dict .pt)")
    return OccupancyModel(cfg, net, threads=threads)
