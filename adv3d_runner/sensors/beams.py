"""Beam tables of real spinning LiDARs and a configurable generic one.

A :class:`LidarModel` holds the per-laser elevation angles (and azimuth offsets where the
manufacturer publishes them), the number of azimuth columns per revolution, and the default
effects used by :mod:`adv3d_runner.sensors.lidar`: max range, Gaussian range noise (1 sigma)
and ray-drop probability. All angles are radians, ranges metres.

Sources of the tables:

- ``hdl64``: Velodyne HDL-64E (S2). Elevation of each of the 64 lasers, in laser-id order, is the
  ``vert_correction`` of a published factory calibration (ros-drivers/velodyne
  ``velodyne_pointcloud/params/64e_utexas.yaml``): +2.02 deg to -24.71 deg, two blocks with
  ~1/3 deg and ~1/2 deg spacing, matching the manual's +2 to -24.8 deg vertical field of view.
  Azimuth resolution 0.1728 deg at 10 Hz -> 2083 columns (133,312 rays). Range 120 m, accuracy
  < 2 cm (manual), so sigma 0.02 m. Per-laser azimuth offsets are ignored (set to zero).
- ``vlp32c``: Velodyne VLP-32C. The 32 non-uniform elevations (-25 to +15 deg) and the
  per-laser azimuth offsets (+-1.4 / +-4.2 deg) of the VLP-32C user manual (laser-id order).
  0.2 deg at 10 Hz -> 1800 columns. Range 200 m, accuracy +-3 cm.
- ``os1-128``: Ouster OS1-128-like: 128 uniformly spaced beams over 45 deg (+22.5 to
  -22.5 deg), 1024 columns at 10 Hz (the common 1024x10 mode), 120 m, sigma 0.03 m. The exact
  per-unit ``beam_altitude_angles`` vary; this table is the nominal uniform layout.
- ``generic``: built by :func:`generic_model` (n beams uniformly over [fov_down, fov_up]).

The ray-drop defaults (a few percent) are simulation choices, not manufacturer figures: real
sensors lose returns on dark, wet or specular surfaces and at grazing angles.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import ConfigError
from ..geometry.angles import wrap_angle

__all__ = ["LidarModel", "MODELS", "get_model", "generic_model", "model_names"]


@dataclass(frozen=True)
class LidarModel:
    """A spinning LiDAR's beam table and default effects.

    Attributes:
        name: model key (``hdl64``, ``vlp32c``, ``os1-128``, ``generic-...``).
        elevations: per-laser elevation angles, radians, laser-id order (tuple of B floats).
        azimuth_offsets: per-laser azimuth offsets added to the column azimuth, radians (B,).
        columns: azimuth steps per revolution (the frame is one full revolution).
        max_range: farthest return, metres.
        min_range: nearest return, metres (closer hits give no return).
        range_noise: 1-sigma Gaussian range noise, metres.
        ray_drop: probability that a return is lost.
        source: where the table comes from (documentation).
    """

    name: str
    elevations: tuple[float, ...]
    azimuth_offsets: tuple[float, ...]
    columns: int
    max_range: float
    min_range: float = 0.5
    range_noise: float = 0.02
    ray_drop: float = 0.02
    source: str = ""

    def __post_init__(self) -> None:
        if len(self.elevations) == 0:
            raise ConfigError(f"LiDAR model {self.name!r}: needs at least one beam")
        if len(self.azimuth_offsets) != len(self.elevations):
            raise ConfigError(f"LiDAR model {self.name!r}: {len(self.azimuth_offsets)} azimuth offsets for "
                              f"{len(self.elevations)} beams")
        if self.columns < 1:
            raise ConfigError(f"LiDAR model {self.name!r}: columns must be >= 1 (got {self.columns})")
        if not (self.max_range > self.min_range >= 0):
            raise ConfigError(f"LiDAR model {self.name!r}: need max_range > min_range >= 0 "
                              f"(got {self.max_range}, {self.min_range})")
        if self.range_noise < 0 or not (0 <= self.ray_drop < 1):
            raise ConfigError(f"LiDAR model {self.name!r}: need range_noise >= 0 and 0 <= ray_drop < 1")

    @property
    def beams(self) -> int:
        """Number of lasers B."""
        return len(self.elevations)

    @property
    def rays(self) -> int:
        """Rays per frame, B x columns."""
        return self.beams * self.columns

    def rings(self) -> np.ndarray:
        """(B,) int16 ring index of each laser: 0 = lowest elevation (ROS velodyne convention)."""
        order = np.argsort(np.asarray(self.elevations), kind="stable")
        ring = np.empty(self.beams, dtype=np.int16)
        ring[order] = np.arange(self.beams, dtype=np.int16)
        return ring

    def ray_table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All rays of one revolution in the sensor frame.

        Returns:
            directions: (N, 3) float64 unit vectors, N = columns x beams, column-major
                (all beams of column 0, then column 1, ...).
            ring: (N,) int16 ring index of each ray.
            azimuth: (N,) float64 azimuth of each ray in the sensor frame, radians in [-pi, pi).
        """
        col_az = np.arange(self.columns) * (2.0 * np.pi / self.columns)
        az = col_az[:, None] + np.asarray(self.azimuth_offsets)[None, :]
        az = wrap_angle(az)
        el = np.broadcast_to(np.asarray(self.elevations)[None, :], az.shape)
        cos_el = np.cos(el)
        directions = np.stack([cos_el * np.cos(az), cos_el * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
        ring = np.broadcast_to(self.rings()[None, :], az.shape).reshape(-1).copy()
        return directions, ring, az.reshape(-1)

    def with_overrides(self, **changes: object) -> "LidarModel":
        """A copy with some fields changed (e.g. ``columns=500`` for a fast test sensor)."""
        return replace(self, **changes)


_DEG = np.pi / 180.0

# Velodyne HDL-64E S2 factory calibration (ros-drivers/velodyne 64e_utexas.yaml), vert_correction
# in radians, laser ids 0..63.
_HDL64_VERT = (
    -0.124932751059532, -0.118993431329727, 0.0055470340885222, 0.0114863449707627,
    -0.113056324422359, -0.107121199369431, -0.148716226220131, -0.142765983939171,
    -0.101187855005264, -0.0952560678124428, -0.136818811297417, -0.130874469876289,
    -0.05375986546278, -0.0478330813348293, -0.0893256440758705, -0.0833963677287102,
    -0.0419059917330742, -0.035978376865387, -0.0774680152535439, -0.0715404152870178,
    -0.0300500374287367, -0.024120757356286, -0.0656133219599724, -0.0596865378320217,
    0.0174280721694231, 0.0233724191784859, -0.0181903336197138, -0.0122585473582149,
    0.0293195936828852, 0.0352698266506195, -0.00632520206272602, -0.000390077300835401,
    -0.396850973367691, -0.387918144464493, -0.200955957174301, -0.192023113369942,
    -0.378992766141891, -0.370074152946472, -0.43128889799118, -0.423701733350754,
    -0.361161530017853, -0.352254241704941, -0.414742022752762, -0.405792057514191,
    -0.28999200463295, -0.281101644039154, -0.343351542949677, -0.334452718496323,
    -0.272210210561752, -0.26331701874733, -0.323895305395126, -0.316663861274719,
    -0.254421383142471, -0.245522528886795, -0.307772427797318, -0.298882067203522,
    -0.183082059025764, -0.17413204908371, -0.236619830131531, -0.22771255671978,
    -0.16517236828804, -0.156202226877213, -0.218799933791161, -0.209881335496902,
)

# Velodyne VLP-32C user manual: (elevation deg, azimuth offset deg) per laser id 0..31.
_VLP32C_TABLE = (
    (-25.0, 1.4), (-1.0, -4.2), (-1.667, 1.4), (-15.639, -1.4), (-11.31, 1.4), (0.0, -1.4),
    (-0.667, 4.2), (-8.843, -1.4), (-7.254, 1.4), (0.333, -4.2), (-0.333, 1.4), (-6.148, -1.4),
    (-5.333, 4.2), (1.333, -1.4), (0.667, 4.2), (-4.0, -1.4), (-4.667, 1.4), (1.667, -4.2),
    (1.0, 1.4), (-3.667, -4.2), (-3.333, 4.2), (3.333, -1.4), (2.333, 1.4), (-2.667, -1.4),
    (-3.0, 1.4), (7.0, -1.4), (4.667, 1.4), (-2.333, -4.2), (-2.0, 4.2), (15.0, -1.4),
    (10.333, 1.4), (-1.333, -1.4),
)


def generic_model(
    beams: int = 32,
    fov_up_deg: float = 10.0,
    fov_down_deg: float = -30.0,
    columns: int = 1024,
    max_range: float = 100.0,
    *,
    min_range: float = 0.5,
    range_noise: float = 0.02,
    ray_drop: float = 0.0,
    name: str | None = None,
) -> LidarModel:
    """A configurable spinning LiDAR: ``beams`` lasers evenly spaced over [fov_down, fov_up].

    With one beam the laser points at ``fov_up_deg``.
    """
    if beams < 1:
        raise ConfigError(f"generic LiDAR: beams must be >= 1 (got {beams})")
    if beams == 1:
        elev = np.array([fov_up_deg]) * _DEG
    else:
        elev = np.linspace(fov_up_deg, fov_down_deg, beams) * _DEG
    return LidarModel(
        name=name or f"generic-{beams}",
        elevations=tuple(float(e) for e in elev),
        azimuth_offsets=(0.0,) * beams,
        columns=int(columns),
        max_range=float(max_range),
        min_range=float(min_range),
        range_noise=float(range_noise),
        ray_drop=float(ray_drop),
        source=f"generic: {beams} beams uniform over [{fov_down_deg}, {fov_up_deg}] deg, {columns} columns",
    )


MODELS: dict[str, LidarModel] = {
    "hdl64": LidarModel(
        name="hdl64",
        elevations=_HDL64_VERT,
        azimuth_offsets=(0.0,) * 64,
        columns=2083,
        max_range=120.0,
        min_range=0.9,
        range_noise=0.02,
        ray_drop=0.02,
        source="Velodyne HDL-64E S2: factory calibration vert_correction (ros-drivers/velodyne "
               "64e_utexas.yaml), 0.1728 deg azimuth at 10 Hz, 120 m, <2 cm accuracy",
    ),
    "vlp32c": LidarModel(
        name="vlp32c",
        elevations=tuple(e * _DEG for e, _ in _VLP32C_TABLE),
        azimuth_offsets=tuple(a * _DEG for _, a in _VLP32C_TABLE),
        columns=1800,
        max_range=200.0,
        min_range=1.0,
        range_noise=0.03,
        ray_drop=0.02,
        source="Velodyne VLP-32C user manual: 32 lasers -25..+15 deg with azimuth offsets, 0.2 deg "
               "at 10 Hz, 200 m, +-3 cm",
    ),
    "os1-128": generic_model(
        128, 22.5, -22.5, 1024, 120.0, min_range=0.3, range_noise=0.03, ray_drop=0.02, name="os1-128",
    ).with_overrides(source="Ouster OS1-128-like: 128 uniform beams over +-22.5 deg, 1024 columns at "
                            "10 Hz, 120 m, sigma 3 cm (nominal layout)"),
}


def model_names() -> list[str]:
    """Keys accepted by :func:`get_model` (besides ``generic`` / ``generic-N``)."""
    return sorted(MODELS)


def get_model(name: str, **overrides: object) -> LidarModel:
    """Look up a model by key; ``generic`` or ``generic-N`` builds a generic N-beam model.

    Args:
        name: ``hdl64``, ``vlp32c``, ``os1-128`` (aliases ``hdl-64e``, ``vlp-32c``,
            ``os128``), ``generic`` or ``generic-N``.
        overrides: fields to change, e.g. ``columns=360, ray_drop=0``.
    """
    key = name.lower().replace("_", "-")
    key = {"hdl-64e": "hdl64", "hdl64e": "hdl64", "vlp-32c": "vlp32c", "os128": "os1-128",
           "os1128": "os1-128"}.get(key, key)
    if key in MODELS:
        model = MODELS[key]
    elif key == "generic" or key.startswith("generic-"):
        tail = key.partition("-")[2]
        try:
            beams = int(tail) if tail else 32
        except ValueError:
            raise ConfigError(f"unknown LiDAR model {name!r}: generic-N needs an integer N") from None
        model = generic_model(beams)
    else:
        raise ConfigError(f"unknown LiDAR model {name!r}; known: {', '.join(model_names())}, generic-N")
    return model.with_overrides(**overrides) if overrides else model
