"""PIXOR-like bird's-eye-view (BEV) LiDAR vehicle detector (Autonomy-A perception).

Pipeline (Yang et al., "PIXOR", CVPR 2018, simplified to one stage and a small network):

1. **Voxelise** the ego-frame points on a BEV grid (``DetectorConfig.resolution`` m per cell,
   the knob; x in ``x_range`` forward, y in ``y_range`` left): one occupancy channel per height
   slice (``z_edges``, metres above the ground) plus one log point-density channel. Points below
   the first edge (the road) and above the last are ignored.
2. A small fully-convolutional **backbone** (three stride-2 stages, a top-down merge of the last
   two) outputs, at 1/``out_stride`` of the grid, a vehicle **score** map and a 6-channel
   **box** map per cell: ``(dx/2, dy/2, log l - 1.5, log w - 0.65, cos yaw, sin yaw)``, the
   offset from the cell centre to the box centre (m), the size and heading of the box.
3. **Decode**: cells scoring above ``score_threshold`` (top ``pre_nms`` by score) each give a
   box; greedy rotated NMS (BEV IoU from :mod:`adv3d_runner.geometry.boxes`) keeps the best box
   of each cluster, refined by the score-weighted mean of the cluster's boxes ("box voting").

Boxes are ``(x, y, length, width, yaw)`` in the **ego frame** (see
:mod:`adv3d_runner.autonomy.interface`). Weights ship as a ``state_dict`` ``.pt`` loaded with
``torch.load(..., weights_only=True)`` (no pickle), next to a ``config.json``.

Numpy-only parts (grid, voxelisation, training targets, decoding, NMS) are module functions so
tests and the data pipeline use them without a network.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from ..errors import ConfigError, FileFormatError
from ..fileio import REPO_ROOT
from ..geometry.boxes import _clip_candidates, _corners, _finite_areas, _ordered_area, iou_paired
from ..jit import kernel
from ..validate import Node, check_header
from .interface import Detections

DEFAULT_MODEL_DIR = REPO_ROOT / "assets" / "models" / "detector"
WEIGHTS_NAME = "detector.pt"
CONFIG_NAME = "config.json"
CONFIG_FORMAT = "adv3d-detector-config"
CONFIG_VERSION = 1
# Regression parameterisation constants (log of typical car length / width; offsets in units
# of 2 m) so every target is O(1).
_LOG_L0, _LOG_W0, _OFFSET_SCALE = 1.5, 0.65, 2.0
_DOWNSAMPLE = 8  # the backbone's coarsest stride: grid sizes are padded to a multiple of it
MAX_GRID_CELLS = 4096 * 4096  # the shipped grid is 288 x 192
#: Largest weights file loaded (the shipped one is ~0.6 MB).
MAX_WEIGHTS_BYTES = 2**30


def _range(node: Node) -> tuple[float, float]:
    """A ``[low, high]`` extent in m (low < high, within 1 km)."""
    lo, hi = node.numbers(length=2, lo=-1000.0, hi=1000.0)
    if not lo < hi:
        node.fail("[low, high] with low < high (m)", [lo, hi])
    return float(lo), float(hi)


def grid_params(node: Node, dflt: Any) -> dict[str, Any]:
    """The BEV input grid's fields of a model config (the detector's and the occupancy model's):
    ``resolution``, ``x_range``, ``y_range``, ``z_edges`` read from ``node`` (an object of
    parameters), each typed and bounded, ``dflt``'s value where absent. ``z_edges`` comes back
    as a (E,) array, checked increasing by :func:`build_grid_config` once every field is read."""
    g = node.get
    return {"resolution": g("resolution", dflt.resolution).number(lo=0.01, hi=10.0),
            "x_range": _range(g("x_range", list(dflt.x_range))),
            "y_range": _range(g("y_range", list(dflt.y_range))),
            "z_edges": g("z_edges", list(dflt.z_edges)).numbers(min_length=2, lo=-100.0, hi=100.0)}


def build_grid_config(cls: type, node: Node, kw: dict[str, Any], what: str) -> Any:
    """``cls(**kw)`` for a config read from ``node`` (``kw`` with :func:`grid_params`' fields):
    increasing ``z_edges``, the class's own checks (a ``ConfigError`` becomes a
    ``FileFormatError`` naming ``node``, expected ``valid <what>``), and a grid of at most
    :data:`MAX_GRID_CELLS` cells."""
    if np.any(np.diff(kw["z_edges"]) <= 0):
        node.get("z_edges").fail("increasing height edges", np.asarray(kw["z_edges"]).tolist())
    try:
        cfg = cls(**kw)
    except ConfigError as exc:
        node.fail(f"valid {what}", str(exc))
    nx, ny = cfg.grid_shape
    if nx * ny > MAX_GRID_CELLS:
        node.fail(f"a BEV grid of at most {MAX_GRID_CELLS} cells (x_range, y_range, resolution)", f"{nx} x {ny}")
    return cfg


def read_model_config(path: str | Path, config_name: str, config_format: str, version: int,
                      missing: str) -> tuple[Path, Node]:
    """A model folder's (or its config file's) ``config.json``: its path and parsed document,
    header checked. ``missing``: what the error says was expected when there is no file."""
    path = Path(path)
    cfg_path = path / config_name if path.is_dir() else path
    if not cfg_path.is_file():
        raise FileFormatError(cfg_path, "$", missing, "no such file")
    doc = Node.load(cfg_path)
    check_header(doc, config_format, (version,))
    return cfg_path, doc


def load_state_into(net: nn.Module, doc: Node, cfg_path: Path, weights_name: str, what: str) -> None:
    """Load the weights file that ``doc`` (the model's config, at ``cfg_path``) names, default
    ``weights_name``, inside the model folder, into ``net`` (strict; :func:`load_weights`).

    Raises:
        FileFormatError: a path outside the folder, a file :func:`load_weights` refuses, or
            weights that do not match ``net``'s architecture."""
    weights = doc.get("weights", weights_name).file_in(cfg_path.parent, inside="the model folder")
    state = load_weights(weights, what)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise FileFormatError(weights, "$", f"weights matching the architecture in {cfg_path.name}",
                              str(exc).splitlines()[0][:200]) from None


def load_weights(path: Path, what: str):
    """A tensor-only state_dict from ``path`` (a regular file of at most
    :data:`MAX_WEIGHTS_BYTES`), read with ``torch.load(weights_only=True)`` (no pickle).

    Raises:
        FileFormatError: missing, not a regular file, too large, or not a plain tensor dict.
    """
    from ..fileio import check_regular_file

    st = check_regular_file(path, what)
    if st.st_size > MAX_WEIGHTS_BYTES:
        raise FileFormatError(path, "$", f"{what} of at most {MAX_WEIGHTS_BYTES // 2**20} MiB", st.st_size)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle.UnpicklingError & co: not a plain tensor state_dict
        raise FileFormatError(path, "$", "a tensor-only state_dict loadable with torch.load(weights_only=True)",
                              f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise FileFormatError(path, "$", "a dict of tensors (state_dict)", type(state).__name__)
    return state


@dataclass
class DetectorConfig:
    """Architecture, input grid and decoding parameters (stored in ``config.json``).

    Attributes:
        resolution: BEV cell size, m (the speed/accuracy knob: 0.2, 0.25, 0.4, ...).
        x_range, y_range: grid extent in the ego frame, m; the far end is extended so the cell
            counts are multiples of 8.
        z_edges: height slice edges above the ground, m (one occupancy channel per slice).
        channels: backbone stage widths (strides 2, 4, 8).
        head_channels: width of the merged stride-``out_stride`` feature map.
        out_stride: output cell = ``out_stride`` x ``resolution`` m (4 or 2).
        score_threshold: minimum score of a kept detection (the operating point for the
            tracker; AP is measured with a lower threshold, see ``detector_train``).
        nms_iou: rotated-BEV IoU above which a lower-scored box is suppressed.
        pre_nms: at most this many cells (highest scores) enter NMS.
        max_detections: at most this many boxes per frame.
    """

    resolution: float = 0.25
    x_range: tuple[float, float] = (-12.0, 60.0)
    y_range: tuple[float, float] = (-24.0, 24.0)
    z_edges: tuple[float, ...] = (0.3, 0.8, 1.3, 1.8, 2.3, 3.0, 4.5)
    channels: tuple[int, int, int] = (16, 32, 64)
    head_channels: int = 48
    out_stride: int = 4
    score_threshold: float = 0.4
    nms_iou: float = 0.1
    pre_nms: int = 300
    max_detections: int = 100

    def __post_init__(self) -> None:
        self.x_range = tuple(float(v) for v in self.x_range)
        self.y_range = tuple(float(v) for v in self.y_range)
        self.z_edges = tuple(float(v) for v in self.z_edges)
        self.channels = tuple(int(v) for v in self.channels)
        if not (self.resolution > 0 and math.isfinite(self.resolution)):
            raise ConfigError(f"detector resolution must be > 0 m, got {self.resolution}")
        if self.out_stride not in (2, 4):
            raise ConfigError(f"out_stride must be 2 or 4, got {self.out_stride}")
        if len(self.channels) != 3 or len(self.z_edges) < 2 or np.any(np.diff(self.z_edges) <= 0):
            raise ConfigError("channels must have 3 entries and z_edges be increasing (>= 2 edges)")

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(nx, ny) input cells (multiples of 8)."""
        def cells(lo: float, hi: float) -> int:
            n = int(math.ceil((hi - lo) / self.resolution - 1e-9))
            return int(math.ceil(n / _DOWNSAMPLE) * _DOWNSAMPLE)
        return cells(*self.x_range), cells(*self.y_range)

    @property
    def out_shape(self) -> tuple[int, int]:
        nx, ny = self.grid_shape
        return nx // self.out_stride, ny // self.out_stride

    @property
    def in_channels(self) -> int:
        return len(self.z_edges) - 1 + 1

    @property
    def out_cell(self) -> float:
        return self.resolution * self.out_stride

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict | Node, path: str | Path | None = None) -> "DetectorConfig":
        """Build from the ``detector`` object of a model's config.json: every field typed and
        bounded (unknown keys refused), the grid at most :data:`MAX_GRID_CELLS` cells."""
        node = d if isinstance(d, Node) else Node(d, "$.detector", path)
        node.object("an object of detector parameters")
        node.check_keys(cls.__dataclass_fields__)
        dflt = cls()
        g = node.get
        kw: dict[str, Any] = {
            **grid_params(node, dflt),
            "channels": [c.integer(lo=1, hi=4096) for c in g("channels", list(dflt.channels)).items(length=3)],
            "head_channels": g("head_channels", dflt.head_channels).integer(lo=1, hi=4096),
            "out_stride": g("out_stride", dflt.out_stride).integer(lo=2, hi=4),
            "score_threshold": g("score_threshold", dflt.score_threshold).number(lo=0.0, hi=1.0),
            "nms_iou": g("nms_iou", dflt.nms_iou).number(lo=0.0, hi=1.0),
            "pre_nms": g("pre_nms", dflt.pre_nms).integer(lo=1, hi=1_000_000),
            "max_detections": g("max_detections", dflt.max_detections).integer(lo=1, hi=100_000),
        }
        return build_grid_config(cls, node, kw, "detector parameters")


# ----------------------------------------------------------------------------- numpy parts

def voxelize(points: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """BEV input tensor of one frame.

    Args:
        points: (P, 3|4) x, y, z [, intensity] in the ego frame (m); P may be 0. float32 or
            float64 (the binning arithmetic is done in that type); other dtypes are converted
            to float64.
        cfg: grid parameters.
    Returns:
        (C, nx, ny) float32: C - 1 height-slice occupancies in {0, 1} and log(1 + n) / log(64)
        of the number n of points (all slices) per column.
    """
    nx, ny = cfg.grid_shape
    nz = len(cfg.z_edges) - 1
    out = np.zeros((nz + 1, nx, ny), np.float32)
    p = np.asarray(points)
    if p.size == 0:
        return out
    p = p.reshape(len(p), -1)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    # Grid origin, cell size and height edges in the points' type: numpy did (x - x0) / res in
    # float32 for float32 points.
    grid = np.array([cfg.x_range[0], cfg.y_range[0], cfg.resolution], p.dtype)
    _bin_points(p, grid, np.asarray(cfg.z_edges, p.dtype), _DENSITY, out)
    return out


#: The density channel by point count n = 0..64: min(log1p(n) / log(64), 1) as numpy computes
#: it (1.0 from n = 63 on), float32.
_DENSITY = np.minimum(np.log1p(np.arange(65)) / np.log(64.0), 1.0).astype(np.float32)


@kernel
def _bin_points(p: np.ndarray, grid: np.ndarray, edges: np.ndarray, density: np.ndarray,
                out: np.ndarray) -> None:
    """Fill the zeroed voxel grid ``out`` (nz + 1, nx, ny) float32 from points ``p`` (P, >= 3).

    ``grid``: x0, y0 (m, the grid's lower corner) and the cell size (m), in ``p``'s dtype;
    ``edges`` (nz + 1,) height slice edges (m); ``density``: :data:`_DENSITY`. A point with
    edges[0] <= z < edges[-1] falls in cell floor((x - x0) / res), floor((y - y0) / res) (in
    ``p``'s arithmetic) and slice k with edges[k] <= z < edges[k + 1]; points outside the grid
    are dropped.

    Compiled: one pass over ~110k returns instead of a dozen numpy passes and two bincounts.
    """
    nz = out.shape[0] - 1
    nx, ny = out.shape[1], out.shape[2]
    count = np.zeros((nx, ny), np.int64)
    x0, y0, res = grid[0], grid[1], grid[2]
    for k in range(p.shape[0]):
        z = p[k, 2]
        if not (z >= edges[0] and z < edges[nz]):
            continue
        fx = np.floor((p[k, 0] - x0) / res)
        fy = np.floor((p[k, 1] - y0) / res)
        if not (fx >= 0 and fx < nx and fy >= 0 and fy < ny):
            continue
        iz = 0  # the last e with edges[e] <= z (edges increase; edges[0] <= z < edges[nz])
        while edges[iz + 1] <= z:
            iz += 1
        ix, iy = int(fx), int(fy)
        out[iz, ix, iy] = 1.0
        count[ix, iy] += 1
    for ix in range(nx):
        for iy in range(ny):
            out[nz, ix, iy] = density[min(count[ix, iy], 64)]


def cell_centres(cfg: DetectorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Ego-frame centres of the output cells: x (ox,), y (oy,) in m."""
    ox, oy = cfg.out_shape
    c = cfg.out_cell
    return cfg.x_range[0] + (np.arange(ox) + 0.5) * c, cfg.y_range[0] + (np.arange(oy) + 0.5) * c


def encode_targets(boxes: np.ndarray, cfg: DetectorConfig, ignore_boxes: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Training targets on the output grid.

    A cell is positive when its centre lies inside a ground-truth box (the cell holding the box
    centre always is, so small boxes on coarse grids keep one); it then regresses that box
    (the box whose centre is nearest when boxes overlap). Cells inside ``ignore_boxes``
    (vehicles with too few LiDAR points to be detectable) and not positive get no score loss.

    Args:
        boxes: (G, 5) ego-frame boxes to detect. ignore_boxes: (I, 5) or None.
    Returns:
        score (ox, oy) float32 in {0, 1}; weight (ox, oy) float32 (0 = ignored);
        reg (6, ox, oy) float32 regression targets (meaningful where score = 1).
    """
    ox, oy = cfg.out_shape
    cx, cy = cell_centres(cfg)
    score = np.zeros((ox, oy), np.float32)
    weight = np.ones((ox, oy), np.float32)
    reg = np.zeros((6, ox, oy), np.float32)
    best = np.full((ox, oy), np.inf)
    c = cfg.out_cell

    def cells_in(box: np.ndarray):
        x, y, l, w, yaw = (float(v) for v in box)
        r = 0.5 * math.hypot(l, w)
        i0, i1 = np.searchsorted(cx, [x - r, x + r])
        j0, j1 = np.searchsorted(cy, [y - r, y + r])
        if i1 <= i0 or j1 <= j0:
            return None
        gx, gy = np.meshgrid(cx[i0:i1], cy[j0:j1], indexing="ij")
        dx, dy = gx - x, gy - y
        u = np.cos(yaw) * dx + np.sin(yaw) * dy
        v = -np.sin(yaw) * dx + np.cos(yaw) * dy
        inside = (np.abs(u) <= 0.5 * l) & (np.abs(v) <= 0.5 * w)
        return i0, j0, inside, dx, dy

    if ignore_boxes is not None:
        for box in np.asarray(ignore_boxes, np.float64).reshape(-1, 5):
            got = cells_in(box)
            if got is not None:
                i0, j0, inside, _, _ = got
                sub = weight[i0:i0 + inside.shape[0], j0:j0 + inside.shape[1]]
                sub[inside] = 0.0
    for box in np.asarray(boxes, np.float64).reshape(-1, 5):
        got = cells_in(box)
        i0, j0 = 0, 0
        if got is None:
            inside = None
        else:
            i0, j0, inside, dx, dy = got
            # The cell holding the centre is always positive.
            ic = int(np.floor((box[0] - cfg.x_range[0]) / c)) - i0
            jc = int(np.floor((box[1] - cfg.y_range[0]) / c)) - j0
            if 0 <= ic < inside.shape[0] and 0 <= jc < inside.shape[1]:
                inside[ic, jc] = True
        if inside is None or not inside.any():
            continue
        ii, jj = np.nonzero(inside)
        gi, gj = ii + i0, jj + j0
        d2 = dx[ii, jj] ** 2 + dy[ii, jj] ** 2
        take = d2 < best[gi, gj]
        gi, gj, ii, jj = gi[take], gj[take], ii[take], jj[take]
        best[gi, gj] = d2[take]
        score[gi, gj] = 1.0
        weight[gi, gj] = 1.0
        reg[0, gi, gj] = -dx[ii, jj] / _OFFSET_SCALE
        reg[1, gi, gj] = -dy[ii, jj] / _OFFSET_SCALE
        reg[2, gi, gj] = math.log(max(box[2], 0.1)) - _LOG_L0
        reg[3, gi, gj] = math.log(max(box[3], 0.1)) - _LOG_W0
        reg[4, gi, gj] = math.cos(box[4])
        reg[5, gi, gj] = math.sin(box[4])
    return score, weight, reg


def decode_boxes(reg: np.ndarray, cfg: DetectorConfig, ii: np.ndarray, jj: np.ndarray) -> np.ndarray:
    """Boxes (K, 5) predicted by output cells (ii, jj) from the box map ``reg`` (6, ox, oy)."""
    cx, cy = cell_centres(cfg)
    # contiguous rows: numpy 1.26's arctan2 on strided float64 rows gives results that depend on
    # where the array lands in memory (one rounding step in a few elements: the same frame
    # decoded twice could differ); on contiguous rows it does not
    r = np.ascontiguousarray(np.asarray(reg, np.float64)[:, ii, jj])
    x = cx[ii] + _OFFSET_SCALE * r[0]
    y = cy[jj] + _OFFSET_SCALE * r[1]
    length = np.exp(np.clip(r[2] + _LOG_L0, -3.0, 4.0))
    width = np.exp(np.clip(r[3] + _LOG_W0, -3.0, 3.0))
    yaw = np.arctan2(r[5], r[4])
    return np.stack([x, y, length, width, yaw], axis=1)


def rotated_nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, max_keep: int | None = None,
                vote: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Greedy non-maximum suppression on rotated BEV boxes.

    Args:
        boxes: (K, 5). scores: (K,).
        iou_threshold: a box whose IoU with a kept, higher-scored box exceeds this is dropped.
        max_keep: keep at most this many.
        vote: replace each kept box by the score-weighted mean of its cluster (itself and the
            boxes it suppressed): centre, log size and heading (as a unit vector).
    Returns:
        boxes (M, 5) and scores (M,) of the kept boxes, by decreasing score.

    The same bits as :func:`rotated_nms_numpy` (its definition, and the test's reference), lazily:
    only the pairs that the greedy pass consults (a keeper against the boxes still alive near
    it, about a sixth of the near pairs of a detector frame) get their IoU, one compiled call
    and one ``np.arctan2`` per keeper (:func:`_nms_advance`). The corners' cos and sin, the
    candidates' arctan2 and the radii's hypot stay numpy's, applied elementwise to the same
    values as there. The near test (centre distance below the sum of the radii) is decided
    from squared distances where the margin is safe (relative 1e-9, far above rounding) and
    falls back to :func:`rotated_nms_numpy` for any other case (non-finite or tiny boxes, a
    distance within that margin). 0.59 -> 0.24 ms per call (50 captured calls of
    ``highway-benchmark-000010``; docs/detector.md).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
    scores = np.asarray(scores, np.float64).reshape(-1)
    n = len(boxes)
    if n == 0:
        return np.zeros((0, 5)), np.zeros(0)
    order = np.argsort(-scores, kind="stable")
    sb, ss = boxes[order], scores[order]
    geo = np.empty((n, 7))
    geo[:, :5] = sb
    geo[:, 5] = 0.5 * np.hypot(np.maximum(sb[:, 2], 0), np.maximum(sb[:, 3], 0))
    geo[:, 6] = _finite_areas(sb)
    corners = _corners(sb, np.cos(sb[:, 4]), np.sin(sb[:, 4]))
    work = np.zeros((4, n), np.int64)
    st = np.zeros(6, np.int64)
    thr = float(iou_threshold)
    mk = n if max_keep is None else int(max_keep)
    rel, valid, count = _nms_advance(geo, corners, thr, mk, work, st, _NO_REL, _NO_VALID, _NO_COUNT, _NO_ANG)
    while len(count):
        ang = np.arctan2(rel[..., 1], rel[..., 0])
        rel, valid, count = _nms_advance(geo, corners, thr, mk, work, st, rel, valid, count, ang)
    if st[5]:  # a near test too close to call from squared distances (or non-finite boxes)
        return rotated_nms_numpy(boxes, scores, iou_threshold, max_keep, vote)
    nk = int(st[1])
    keep = work[2, :nk]
    out = sb[keep]
    if vote:
        # each cluster's members in index order (the keeper first, then the boxes it
        # suppressed), from one stable sort of the cluster ids (nk: never reached)
        cluster = np.where(work[0] != 0, work[1], nk)
        members = np.argsort(cluster, kind="stable")
        ends = np.cumsum(np.bincount(cluster, minlength=nk + 1)).tolist()
        if ends[nk - 1] > nk:  # some cluster has more than its keeper: _vote's arithmetic,
            # its elementwise numpy parts (cos of the heading differences, log sizes, sin and
            # cos of the headings) for all boxes at once, its sums and products per cluster
            # on arrays of the same layout, exp once over the clusters
            ids = members[:ends[nk - 1]]
            agree = np.cos(sb[ids, 4] - sb[keep[cluster[ids]], 4]) > 0.5
            logs = np.log(np.maximum(sb[:, 2:4], 1e-3))
            sins, coss = np.sin(sb[:, 4]), np.cos(sb[:, 4])
            voted, logsize = [], np.empty((nk, 2))
            lo = 0
            for m in range(nk):
                hi = ends[m]
                if hi - lo > 1:
                    sel = members[lo:hi][agree[lo:hi]]
                    w = ss[sel]
                    w = w / w.sum()
                    out[m, 0:2] = w @ sb[sel][:, 0:2]
                    logsize[m] = w @ logs[sel]
                    out[m, 4] = math.atan2(w @ sins[sel], w @ coss[sel])
                    voted.append(m)
                lo = hi
            out[voted, 2:4] = np.exp(logsize[voted])
    return out, ss[keep]


_NO_REL = np.zeros((0, 24, 2))
_NO_VALID = np.zeros((0, 24), np.bool_)
_NO_COUNT = np.zeros(0, np.int64)
_NO_ANG = np.zeros((0, 24))


@kernel
def _nms_advance(geo: np.ndarray, corners: np.ndarray, thr: float, max_keep: int, work: np.ndarray,
                 st: np.ndarray, rel: np.ndarray, valid: np.ndarray, count: np.ndarray, ang: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of :func:`rotated_nms`'s greedy pass over boxes sorted by decreasing score.

    Args:
        geo: (n, 7) boxes, radius (half diagonal, numpy's hypot), area (``_finite_areas``).
        corners: (n, 4, 2) ``box_corners`` of the boxes.
        thr: the IoU threshold; max_keep: stop after this many keepers.
        work: (4, n) int64, zeros at the start: dead flags (1: kept or suppressed), the
            cluster id of each box (its keeper's position; meaningful where dead), the keepers,
            and the pending pairs' second boxes.
        st: (6,) int64, zeros at the start: the keeper whose pairs are pending, the number of
            keepers (the current keeper's id while its pairs are pending), the number of
            pending pairs, the next box to scan, done, and "fall back" (a near test within the
            margin, or non-finite values: the caller runs :func:`rotated_nms_numpy`).
        rel, valid, count: the pending pairs' ``_clip_candidates`` (from the previous call) and
            ang (m, 24) their ``np.arctan2(rel[..., 1], rel[..., 0])``; empty on the first call.
    Returns:
        the next keeper's pending pairs' rel, valid, count (keeper box as ``a``, as
        ``iou_paired(boxes[ii], boxes[jj])`` has it); empty when done.

    The pending pairs' IoU is ``iou_paired``'s arithmetic (minimum with both areas, union,
    division by max(union, 1e-12), clip to [0, 1]) and a pair suppresses where it exceeds
    ``thr``; a pair with a zero-area box has IoU 0.
    """
    n = geo.shape[0]
    dead = work[0]
    cluster = work[1]
    keep = work[2]
    js = work[3]
    m = st[2]
    if m > 0:  # the pending pairs of keeper st[0], id st[1]
        i = st[0]
        nk = st[1]
        inter_all = _ordered_area(rel, valid, count, ang)
        aa = geo[i, 6]
        for q in range(m):
            j = js[q]
            ab = geo[j, 6]
            mn = aa if aa <= ab else ab
            x = inter_all[q]
            inter = x if (x != x or x <= mn) else mn
            union = aa + ab - inter
            den = union if (union >= 1e-12 or union != union) else 1e-12
            iou = inter / den
            if iou != iou:
                continue
            if iou < 0.0:
                iou = 0.0
            if iou > 1.0:
                iou = 1.0
            if iou > thr:
                dead[j] = 1
                cluster[j] = nk
        st[2] = 0
        st[1] = nk + 1
        if nk + 1 >= max_keep:
            st[4] = 1
            return rel[:0], valid[:0], count[:0]
    nk = st[1]
    for i in range(st[3], n):
        if dead[i]:
            continue
        dead[i] = 1
        cluster[i] = nk
        keep[nk] = i
        m = 0
        for j in range(i + 1, n):
            if dead[j]:
                continue
            dx = geo[j, 0] - geo[i, 0]
            dy = geo[j, 1] - geo[i, 1]
            r = geo[j, 5] + geo[i, 5]
            d2 = dx * dx + dy * dy
            r2 = r * r
            if not (d2 <= 1.7e308 and r2 <= 1.7e308 and r2 > 1e-200):
                st[5] = 1
                st[4] = 1
                return rel[:0], valid[:0], count[:0]
            if d2 > r2 * (1.0 + 1e-9):
                continue  # hypot(dx, dy) > r: not near
            if not d2 < r2 * (1.0 - 1e-9):
                st[5] = 1
                st[4] = 1
                return rel[:0], valid[:0], count[:0]
            if geo[i, 6] > 0.0 and geo[j, 6] > 0.0:
                js[m] = j
                m += 1
            elif 0.0 > thr:
                dead[j] = 1
                cluster[j] = nk
        st[3] = i + 1
        if m > 0:
            st[0] = i
            st[2] = m
            ca = np.empty((m, 4, 2))
            cb = np.empty((m, 4, 2))
            origin = np.empty((m, 2))
            for q in range(m):
                j = js[q]
                for k in range(4):
                    for d in range(2):
                        ca[q, k, d] = corners[i, k, d]
                        cb[q, k, d] = corners[j, k, d]
                origin[q, 0] = geo[i, 0]
                origin[q, 1] = geo[i, 1]
            return _clip_candidates(ca, cb, origin)
        nk += 1
        st[1] = nk
        if nk >= max_keep:
            break
    st[4] = 1
    return rel[:0], valid[:0], count[:0]


def rotated_nms_numpy(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, max_keep: int | None = None,
                      vote: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rotated_nms` (same arguments and returns) with the IoU of every near pair in one
    batch: the definition, the test's reference, and the fallback."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if len(boxes) == 0:
        return np.zeros((0, 5)), np.zeros(0)
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]
    # The IoU of every pair (i < j) whose circles overlap, in one batch of paired boxes (the
    # same arithmetic per pair as ``iou_pairwise``: every pair here is one its circle test
    # keeps), then the greedy pass over them compiled. (rotated_nms computes only the pairs
    # the greedy pass consults, with one compiled round per keeper.)
    radius = 0.5 * np.hypot(np.maximum(boxes[:, 2], 0), np.maximum(boxes[:, 3], 0))
    with np.errstate(invalid="ignore"):
        near = (np.hypot(boxes[None, :, 0] - boxes[:, None, 0], boxes[None, :, 1] - boxes[:, None, 1])
                < radius[None, :] + radius[:, None])
    ii, jj = np.nonzero(np.triu(near, 1))
    over = iou_paired(boxes.take(ii, axis=0), boxes.take(jj, axis=0)) > iou_threshold
    keep, cluster = _greedy_clusters(len(boxes), ii, jj, over, len(boxes) if max_keep is None else max_keep)
    out = boxes[keep]
    if vote:
        for m, i in enumerate(keep):
            members = np.flatnonzero(cluster == m)  # i first, then the boxes it suppressed
            if len(members) > 1:
                out[m] = _vote(boxes[members], scores[members])
    return out, scores[keep]


@kernel
def _greedy_clusters(n: int, ii: np.ndarray, jj: np.ndarray, over: np.ndarray, max_keep: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The greedy pass of :func:`rotated_nms` over boxes 0..n-1 sorted by decreasing score.

    Args:
        ii, jj: (P,) int64 pairs i < j whose boxes may overlap, sorted by i then j.
        over: (P,) bool, the pair's IoU exceeds the threshold.
        max_keep: stop after this many keepers.
    Returns:
        keep (M,) int64 indices of the kept boxes in order; cluster (n,) int64, the position in
        ``keep`` of the keeper that kept or suppressed each box (-1: never reached).

    Compiled: a Python loop over keepers and pairs cost more than the pairs' IoU.
    """
    alive = np.ones(n, np.bool_)
    cluster = np.full(n, -1, np.int64)
    keep = np.empty(n, np.int64)
    nk = 0
    q = 0
    for i in range(n):
        while q < len(ii) and ii[q] < i:
            q += 1
        if not alive[i]:
            continue
        alive[i] = False
        cluster[i] = nk
        while q < len(ii) and ii[q] == i:
            j = jj[q]
            if alive[j] and over[q]:
                alive[j] = False
                cluster[j] = nk
            q += 1
        keep[nk] = i
        nk += 1
        if nk >= max_keep:
            break
    return keep[:nk], cluster


def _vote(b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The box voting of :func:`rotated_nms`: cluster boxes ``b`` (C, 5), the keeper first, with
    scores ``w`` (C,) -> (5,) the score-weighted mean centre, log size (m) and heading (rad, as
    a unit vector) of the boxes whose heading agrees with the keeper's (within 60 degrees; a
    reversed box would average the heading away)."""
    box = b[0].copy()
    agree = np.cos(b[:, 4] - box[4]) > 0.5
    b, w = b[agree], w[agree]
    w = w / w.sum()
    box[0:2] = w @ b[:, 0:2]
    box[2:4] = np.exp(w @ np.log(np.maximum(b[:, 2:4], 1e-3)))
    box[4] = math.atan2(w @ np.sin(b[:, 4]), w @ np.cos(b[:, 4]))
    return box


def decode(score_map: np.ndarray, reg: np.ndarray, cfg: DetectorConfig,
           score_threshold: float | None = None) -> Detections:
    """Detections (ego frame) from one frame's network outputs.

    Args:
        score_map: (ox, oy) vehicle probability per output cell.
        reg: (6, ox, oy) box map.
        score_threshold: overrides ``cfg.score_threshold``.
    """
    thr = cfg.score_threshold if score_threshold is None else score_threshold
    s = np.asarray(score_map, np.float64)
    flat = s.reshape(-1)
    cand = np.flatnonzero(flat > thr)
    if cand.size == 0:
        return Detections()
    if cand.size > cfg.pre_nms:
        cand = cand[np.argpartition(-flat[cand], cfg.pre_nms - 1)[:cfg.pre_nms]]
    ii, jj = np.unravel_index(cand, s.shape)
    boxes = decode_boxes(reg, cfg, ii, jj)
    boxes, scores = rotated_nms(boxes, flat[cand], cfg.nms_iou, cfg.max_detections)
    return Detections(boxes, np.clip(scores, 0.0, 1.0))


# ----------------------------------------------------------------------------- network

def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class PixorNet(nn.Module):
    """Small PIXOR-style backbone + header.

    Input (B, C, nx, ny); outputs score logits (B, 1, nx/s, ny/s) and box map (B, 6, nx/s, ny/s)
    with s = ``out_stride``.
    """

    def __init__(self, cfg: DetectorConfig):
        super().__init__()
        c1, c2, c3 = cfg.channels
        h = cfg.head_channels
        self.out_stride = cfg.out_stride
        self.stage1 = nn.Sequential(_conv(cfg.in_channels, c1, 2), _conv(c1, c1))           # /2
        self.stage2 = nn.Sequential(_conv(c1, c2, 2), _conv(c2, c2), _conv(c2, c2))          # /4
        self.stage3 = nn.Sequential(_conv(c2, c3, 2), _conv(c3, c3), _conv(c3, c3))          # /8
        skip = c2 if cfg.out_stride == 4 else c1
        self.merge = nn.Sequential(nn.Conv2d(c3 + skip, h, 1, bias=False), nn.BatchNorm2d(h), nn.ReLU(inplace=True),
                                   _conv(h, h))
        self.score = nn.Conv2d(h, 1, 1)
        self.box = nn.Conv2d(h, 6, 1)
        nn.init.constant_(self.score.bias, -4.6)  # prior 1%: stable start for the focal loss
        nn.init.normal_(self.box.weight, std=1e-3)
        nn.init.zeros_(self.box.bias)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f1 = self.stage1(x)
        f2 = self.stage2(f1)
        f3 = self.stage3(f2)
        skip = f2 if self.out_stride == 4 else f1
        f = self.merge(upsample_concat(f3, skip))
        return self.score(f), self.box(f)


def upsample_concat(coarse: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
    """``cat([interpolate(coarse, size=skip's (H, W), mode="nearest"), skip], dim=1)``.

    coarse (B, C, h, w) and skip (B, S, H, W) -> (B, C + S, H, W). Where H, W = 2h, 2w (always
    here: the strides are powers of 2) and no gradient is recorded, each coarse cell is copied
    into its 2 x 2 block of one preallocated tensor: the same values, without the upsampled
    temporary and the concatenation's second copy (0.57 -> 0.37 ms per 0.25 m frame). The
    blocks are written by a compiled loop (:func:`_upsample2_into`) where both tensors are
    contiguous float32 on the CPU: torch's strided 6-D copy took 0.33 of those 0.37 ms, the
    loop 0.09 (docs/detector.md)."""
    B, C, h, w = coarse.shape
    H, W = skip.shape[-2:]
    if torch.is_grad_enabled() or (H, W) != (2 * h, 2 * w):
        return torch.cat([nn.functional.interpolate(coarse, size=(H, W), mode="nearest"), skip], dim=1)
    out = coarse.new_empty((B, C + skip.shape[1], H, W))
    if coarse.dtype == torch.float32 and coarse.device.type == "cpu" and coarse.is_contiguous():
        _upsample2_into(coarse.numpy(), out.numpy())
    else:
        out[:, :C].view(B, C, h, 2, w, 2).copy_(coarse[:, :, :, None, :, None].expand(B, C, h, 2, w, 2))
    out[:, C:].copy_(skip)
    return out


@kernel
def _upsample2_into(src: np.ndarray, dst: np.ndarray) -> None:
    """Each cell of ``src`` (B, C, h, w) copied into its 2 x 2 block of ``dst[:, :C]`` (B, >= C,
    2h, 2w), in place (nearest upsampling by 2: copies, so the same bits)."""
    B, C, h, w = src.shape
    for b in range(B):
        for c in range(C):
            for i in range(h):
                top = dst[b, c, 2 * i]
                for j in range(w):
                    v = src[b, c, i, j]
                    top[2 * j] = v
                    top[2 * j + 1] = v
                dst[b, c, 2 * i + 1, :] = top


# A leaf of torch.fx graphs (fold_batchnorm traces the network): its shape test runs at call time.
torch.fx.wrap("upsample_concat")


# ----------------------------------------------------------------------------- detector

class BevDetector:
    """The learned BEV detector behind the ``Detector`` protocol of
    :mod:`adv3d_runner.autonomy.modular`.

    Args:
        cfg: grid/architecture/decoding parameters.
        net: a :class:`PixorNet` for ``cfg`` (random weights when None).
        threads: torch intra-op threads used by :meth:`detect` (None: leave torch's setting).

    ``inference_net`` is the module :meth:`detect` runs: ``net`` itself, or (models loaded by
    :func:`load_detector`) its copy with the BatchNorms folded in (:func:`fold_batchnorm`).

    ``timings`` holds seconds per step of the last :meth:`detect` call (``voxelize``,
    ``network``, ``decode``), measured with ``clock`` (default ``time.perf_counter``; benchmarks
    on a shared machine set ``time.thread_time``).
    """

    clock = staticmethod(time.perf_counter)

    def __init__(self, cfg: DetectorConfig | None = None, net: PixorNet | None = None, threads: int | None = 1):
        self.cfg = cfg or DetectorConfig()
        self.net = (net or PixorNet(self.cfg)).eval()
        self.inference_net: nn.Module = self.net
        self.threads = threads
        self.timings: dict[str, float] = {}
        #: run the network through :func:`blocked_forward` where it gives the same bits, after
        #: this many calls per input shape (:meth:`_runner`)
        self.blocked = True
        self.blocked_after = 20
        #: "float32" (the trained network's arithmetic) or "bfloat16": the network's weights and
        #: feature maps rounded to bfloat16 (oneDNN's bf16 kernels, float32 accumulation), about
        #: 1.5x faster where the CPU has AVX512-BF16 or AMX and slower where not; other scores
        #: (by up to ~0.005 on the shipped model) and so other results: an option, measured in
        #: docs/performance.md, not the default
        self.precision = "float32"
        self._bf16: tuple[nn.Module, Any] | None = None  # (inference_net, its bfloat16 forward)
        # (inference_net, its flat_forward, per (input shape, threads) the forward chosen and
        # the calls made until the blocked layout's check)
        self._flat: tuple[nn.Module, Any, dict] | None = None

    def _forward(self, grids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.threads is not None and torch.get_num_threads() != self.threads:
            torch.set_num_threads(self.threads)
        x = torch.from_numpy(np.ascontiguousarray(grids))
        with torch.inference_mode():
            if self.precision == "bfloat16":
                logits, box = self._bf16_runner()(x.to(torch.bfloat16))
                logits, box = logits.float(), box.float()
            elif self.precision == "float32":
                logits, box = self._runner(tuple(x.shape))(x)
            else:
                raise ConfigError(f"detector precision must be 'float32' or 'bfloat16', got {self.precision!r}")
            return torch.sigmoid(logits[:, 0]).numpy(), box.numpy()

    def _bf16_runner(self):
        """:func:`flat_forward` of a bfloat16 copy of ``inference_net`` (made once per net)."""
        net = self.inference_net
        if self._bf16 is None or self._bf16[0] is not net:
            import copy

            half = copy.deepcopy(net).to(torch.bfloat16)
            self._bf16 = (net, flat_forward(half) or half)
        return self._bf16[1]

    def _runner(self, shape: tuple[int, ...]):
        """The forward :meth:`_forward` runs on inputs of ``shape``: :func:`flat_forward` of
        ``inference_net`` (the module itself where that declines) for the first
        :attr:`blocked_after` calls, then :func:`blocked_forward` if it gave the same bits as
        :func:`flat_forward` on that shape with this thread count (checked once, on
        :func:`check_input`: two forwards and oneDNN's set-up of the blocked kernels, about
        0.025 CPU-s, which a one-frame command would pay for nothing)."""
        net = self.inference_net
        if self._flat is None or self._flat[0] is not net:
            self._flat = (net, flat_forward(net), {})
        _, flat, chosen = self._flat
        key = (shape, torch.get_num_threads())
        entry = chosen.setdefault(key, [flat or net, 0])  # [forward, calls until the check; None: done]
        if entry[1] is not None:
            entry[1] += 1
            if flat is None or not self.blocked:
                entry[1] = None
            elif entry[1] > self.blocked_after:
                entry[1] = None
                blocked = blocked_forward(net)
                if blocked is not None and same_outputs(flat, blocked, shape):
                    entry[0] = blocked
        return entry[0]

    def detect(self, points: np.ndarray, score_threshold: float | None = None) -> Detections:
        """Vehicles in one LiDAR frame.

        Args:
            points: (P, 3|4) x, y, z [, intensity] in the ego frame, m; P may be 0.
            score_threshold: overrides the configured one.
        Returns:
            :class:`Detections` with boxes (N, 5) in the **ego** frame and scores in [0, 1];
            empty when no point falls in the grid.
        """
        t0 = self.clock()
        grid = voxelize(points, self.cfg)
        t1 = self.clock()
        if not grid[-1].any():  # no point in the grid: nothing to see (and no wasted forward)
            self.timings = {"voxelize": t1 - t0, "network": 0.0, "decode": 0.0}
            return Detections()
        score, box = self._forward(grid[None])
        t2 = self.clock()
        dets = decode(score[0], box[0], self.cfg, score_threshold)
        self.timings = {"voxelize": t1 - t0, "network": t2 - t1, "decode": self.clock() - t2}
        return dets

    def detect_batch(self, frames: Sequence[np.ndarray], score_threshold: float | None = None,
                     batch_size: int = 8) -> list[Detections]:
        """:meth:`detect` over many frames (batched network calls; same results)."""
        out: list[Detections] = []
        for k in range(0, len(frames), batch_size):
            grids = np.stack([voxelize(p, self.cfg) for p in frames[k:k + batch_size]])
            score, box = self._forward(grids)
            for g, s, b in zip(grids, score, box):
                out.append(decode(s, b, self.cfg, score_threshold) if g[-1].any() else Detections())
        return out


def save_detector(det: BevDetector, out_dir: str | Path, extra_config: dict[str, Any] | None = None) -> Path:
    """Write ``detector.pt`` (float32 state_dict) and ``config.json`` into ``out_dir`` (atomic)."""
    from ..fileio import atomic_path, write_json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in det.net.state_dict().items()}
    with atomic_path(out_dir / WEIGHTS_NAME) as tmp:
        torch.save(state, tmp)
    doc = {"format": CONFIG_FORMAT, "version": CONFIG_VERSION, "weights": WEIGHTS_NAME,
           "detector": det.cfg.to_dict()}
    doc.update(extra_config or {})
    write_json(out_dir / CONFIG_NAME, doc)
    return out_dir / WEIGHTS_NAME


def load_detector(path: str | Path = DEFAULT_MODEL_DIR, threads: int | None = 1, precision: str = "float32",
                  **overrides: Any) -> BevDetector:
    """Load a trained detector.

    Args:
        path: the model folder (``config.json`` + weights) or its ``config.json``.
        threads: torch threads for inference (1 = one core, as the episode benchmark assumes).
        precision: :attr:`BevDetector.precision` ("float32", the default, or "bfloat16", which
            gives other results).
        overrides: decoding parameters to change (e.g. ``score_threshold=0.3``).
    Raises:
        FileFormatError: missing/invalid config, or weights that are not a plain tensor
            state_dict (anything needing pickle is refused by ``weights_only=True``).
    """
    cfg_path, doc = read_model_config(path, CONFIG_NAME, CONFIG_FORMAT, CONFIG_VERSION,
                                      "a detector config.json (train one with `adv3d train detector`)")
    params = doc["detector"]
    params = Node({**params.object("an object of detector parameters"), **overrides}, params.path, cfg_path)
    cfg = DetectorConfig.from_dict(params)
    net = PixorNet(cfg)
    load_state_into(net, doc, cfg_path, WEIGHTS_NAME, "detector weights (state_dict .pt)")
    det = BevDetector(cfg, net, threads=threads)
    det.inference_net = fold_batchnorm(net)
    if precision not in ("float32", "bfloat16"):
        raise ConfigError(f"detector precision must be 'float32' or 'bfloat16', got {precision!r}")
    det.precision = precision
    return det


def _graph_steps(net: nn.Module) -> tuple[list[tuple[str, Any, tuple[int, ...]]], tuple[int, ...]] | None:
    """The steps of a :func:`fold_batchnorm` graph in order, or None for anything else.

    For a ``torch.fx.GraphModule`` whose modules are all zero-padded ``Conv2d`` and ``ReLU`` and
    whose ``forward`` is its own: ``(kind, what, args)`` per node, ``kind`` one of ``"conv"``
    (``what`` the Conv2d), ``"relu"`` (``what`` its ``inplace``) or ``"call"`` (``what`` the
    function), ``args`` the indices of the values it takes (0: the input, k: step k's result);
    and the indices of the outputs."""
    if not isinstance(net, torch.fx.GraphModule) or "forward" in vars(net):
        return None
    steps, names, out = [], {}, None
    for node in net.graph.nodes:
        if node.op == "placeholder":
            names[node.name] = len(names)
            continue
        if node.op == "output":
            out = node.args[0]
            break
        if node.kwargs:
            return None
        if node.op == "call_module":
            m = net.get_submodule(node.target)
            if type(m) is nn.Conv2d and m.padding_mode == "zeros" and len(node.args) == 1:
                step = ("conv", m)
            elif type(m) is nn.ReLU and len(node.args) == 1:
                step = ("relu", m.inplace)
            else:
                return None
        elif node.op == "call_function":
            step = ("call", node.target)
        else:
            return None
        if not all(isinstance(a, torch.fx.Node) for a in node.args):
            return None
        steps.append((*step, tuple(names[a.name] for a in node.args)))
        names[node.name] = len(names)
    if out is None or not isinstance(out, tuple) or not all(isinstance(a, torch.fx.Node) for a in out):
        return None
    return steps, tuple(names[a.name] for a in out)


def _run_plan(plan: list[tuple[Any, tuple[int, ...]]], outs: tuple[int, ...]):
    """A forward calling ``fn(*values)`` for each ``(fn, args)`` of ``plan`` in order (value 0 is
    the input, value k step k's result) and returning the values ``outs``. Each value is dropped
    after its last use (as fx's code does): the allocator then reuses its memory while it is
    still in cache."""
    last = {i: k for k, (_, args) in enumerate(plan) for i in args}
    plan = [(fn, args, tuple(i for i in set(args) if last[i] == k and i not in outs))
            for k, (fn, args) in enumerate(plan)]

    def forward(x: torch.Tensor):
        env = [x] + [None] * len(plan)
        for k, (fn, args, done) in enumerate(plan, 1):
            env[k] = fn(*[env[i] for i in args])
            for i in done:
                env[i] = None
        return tuple(env[i] for i in outs)

    return forward


def flat_forward(net: nn.Module):
    """The forward of a :func:`fold_batchnorm` graph as a list of direct calls, or None.

    For a graph :func:`_graph_steps` reads: a function of the input that calls
    ``torch.conv2d`` with each convolution's weight, bias, stride, padding, dilation and groups
    and ``torch.relu_`` / ``torch.relu`` in the graph's order, as the modules' forwards do (the
    same ATen calls, so the same bits), without nn.Module's call machinery (23 module calls a
    frame, ~0.1 ms). The weights are the modules' own tensors, so changing them in place is
    seen. None for anything else."""
    graph = _graph_steps(net)
    if graph is None:
        return None
    steps, outs = graph
    relu = {True: torch.relu_, False: torch.relu}
    plan = [(_conv_call(what) if kind == "conv" else relu[what] if kind == "relu" else what, args)
            for kind, what, args in steps]
    return _run_plan(plan, outs)


def blocked_forward(net: nn.Module):
    """:func:`flat_forward` with the feature maps between the ``k x k`` convolutions (k > 1)
    kept in oneDNN's blocked layout, or None (what :func:`flat_forward` declines, or a torch
    without oneDNN).

    Called on plain NCHW tensors, torch hands each such convolution to oneDNN, which reorders
    its input into its blocked layout, its weights into theirs, and its output back, every
    call (docs/performance.md, "Why the detector costs more on some CPUs"). Here the weights
    are reordered once (so changing the module's weights later is not seen: build it again)
    and a map stays blocked from one convolution (and its ReLU) to the next; it is made plain
    only where a step needs it (the 1 x 1 convolutions, which torch runs itself on one thread,
    the upsampling merge, the outputs). Reorders are copies, so where oneDNN runs the same
    convolution kernels as for plain tensors the outputs are the same bits;
    :class:`BevDetector` checks that per input shape before using it (:func:`same_outputs`)."""
    graph = _graph_steps(net) if torch.backends.mkldnn.is_available() else None
    if graph is None:
        return None
    steps, outs = graph
    blocked = [False] * (len(steps) + 1)  # per value: in the blocked layout
    plan: list[tuple[Any, tuple[int, ...]]] = []
    converted: dict[tuple[int, bool], int] = {}
    position = list(range(len(steps) + 1))  # a value's index in the plan's values

    def take(i: int, want_blocked: bool) -> int:
        """The plan value holding value ``i`` in the wanted layout (adding a conversion)."""
        if blocked[i] == want_blocked:
            return position[i]
        if (i, want_blocked) not in converted:
            plan.append((torch.Tensor.to_mkldnn if want_blocked else torch.Tensor.to_dense, (position[i],)))
            converted[(i, want_blocked)] = len(plan)
        return converted[(i, want_blocked)]

    relu = {True: torch.relu_, False: torch.relu}
    for k, (kind, what, args) in enumerate(steps, 1):
        if kind == "conv" and what.kernel_size != (1, 1):
            plan.append((_blocked_conv_call(what), (take(args[0], True),)))
            blocked[k] = True
        elif kind == "relu":
            plan.append((relu[what], (position[args[0]],)))
            blocked[k] = blocked[args[0]]
            if what:  # in place: a copy in the other layout made before is stale
                converted.pop((args[0], not blocked[k]), None)
        else:
            fn = _conv_call(what) if kind == "conv" else what
            plan.append((fn, tuple(take(i, False) for i in args)))
        position[k] = len(plan)
    out_positions = tuple(take(i, False) for i in outs)
    return _run_plan(plan, out_positions)


def _blocked_conv_call(m: nn.Conv2d):
    """``m(x)`` for ``x`` in oneDNN's layout, the result in that layout:
    ``torch.mkldnn_convolution`` with the weights reordered once (as
    ``torch.utils.mkldnn.MkldnnConv2d`` does)."""
    stride, padding, dilation, groups = m.stride, m.padding, m.dilation, m.groups
    w = torch._C._nn.mkldnn_reorder_conv2d_weight(m.weight.detach().to_mkldnn(), padding, stride, dilation, groups)
    b = None if m.bias is None else m.bias.detach().to_mkldnn()
    return lambda x: torch.mkldnn_convolution(x, w, b, padding, stride, dilation, groups)


def same_outputs(a, b, shape: tuple[int, ...], seed: int = 0) -> bool:
    """Whether forwards ``a`` and ``b`` give the same bits on a seeded random input of ``shape``
    (B, C, nx, ny): a tenth of the cells in (0, 1], as sparse as a LiDAR frame's grid but
    reaching every weight."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g)
    x = torch.where(torch.rand(shape, generator=g) < 0.1, x, torch.zeros(()))
    with torch.inference_mode():
        return all(u.numpy().tobytes() == v.numpy().tobytes() for u, v in zip(a(x), b(x)))


def _conv_call(m: nn.Conv2d):
    """``m(x)`` of a zero-padded Conv2d: ``F.conv2d(x, weight, bias, stride, padding, dilation,
    groups)``, as ``Conv2d._conv_forward`` calls it."""
    w, b, stride, padding, dilation, groups = m.weight, m.bias, m.stride, m.padding, m.dilation, m.groups
    return lambda x: nn.functional.conv2d(x, w, b, stride, padding, dilation, groups)


def fold_batchnorm(net: nn.Module) -> nn.Module:
    """An inference copy of ``net`` with every BatchNorm folded into the convolution before it
    (``torch.fx``'s conv-bn fusion): the same function up to float32 rounding (scores differ by
    ~1e-6), one pass over each feature map less; 6.8 -> 5.3 ms per 0.25 m frame on one core
    (docs/detector.md). Only for a model that is no longer trained: the fused copy has no BatchNorm
    statistics to update and its state_dict is not a :class:`PixorNet`'s."""
    import warnings

    with warnings.catch_warnings():  # the module's imports use torch.jit.script_method, deprecated
        warnings.simplefilter("ignore", DeprecationWarning)
        from torch.fx.experimental.optimization import fuse

    return fuse(net.eval(), inplace=False)


def model_info(path: str | Path = DEFAULT_MODEL_DIR) -> dict:
    """The model folder's config.json as a dict (no torch needed by callers beyond import)."""
    p = Path(path)
    return json.loads(((p / CONFIG_NAME) if p.is_dir() else p).read_text())
