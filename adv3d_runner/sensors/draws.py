"""The LiDAR's random draws, compiled: numpy's ``PCG64`` float32 normals and uniforms, bit for bit.

Why: a frame's sensor effects draw one float32 normal (range noise) and one float32 uniform
(ray drop) per return from the episode's ``numpy.random.Generator``, about 100k of each. numpy
spends ~11 ns per normal (its ziggurat calls the bit generator through a function pointer per
draw) and ~2.5 ns per uniform: 1.5 ms of a closed-loop frame (docs/lidar.md). The same algorithms in
one compiled loop, with the PCG64 step inlined, take a fraction of that.

Same draws. :func:`draw_f32` reads the generator's state, runs numpy's own algorithms on it and
writes the advanced state back, so the values and every later draw from the generator are the
ones ``rng.standard_normal(n, dtype=np.float32)`` then ``rng.random(n, dtype=np.float32)``
would give:

* PCG64 (XSL-RR 128/64, O'Neill's default 128-bit multiplier): the state steps, then the
  output is taken; a 32-bit draw uses the low half of a 64-bit output and keeps the high half
  for the next one (numpy's ``has_uint32`` / ``uinteger``);
* uniform: ``(u32 >> 8) * 2**-24`` in float32;
* normal: numpy's 256-layer float32 ziggurat, its tables taken from numba's copy of numpy's
  (``numba.np.random._constants``); the rare paths call the C library's ``exp`` and
  ``log1pf`` as numpy's C code does.

That the tables and the rare paths match the installed numpy is checked once per process
against numpy itself (:func:`compiled_draws_available`: 2 x 400k normals and uniforms, all
the tail and wedge paths among them, ~30 ms); where it does not (another numpy's algorithm,
another numba without the tables), and for any generator that is not exactly a ``PCG64``, the
draws are numpy's own calls. ``tests/test_draws.py`` compares many seeds, sizes and
interleavings.
"""
from __future__ import annotations

import threading

import numpy as np
from numba import types

from ..jit import kernel

__all__ = ["draw_f32", "compiled_draws_available"]

try:  # numpy's float32 ziggurat tables as numba ships them (checked against numpy below)
    from numba.np.random._constants import fi_float as _FI, ki_float as _KI, wi_float as _WI
    from numba.np.random._constants import ziggurat_nor_inv_r_f as _INV_R, ziggurat_nor_r_f as _R
    _TABLES = (np.ascontiguousarray(_KI, np.uint32), np.ascontiguousarray(_WI, np.float32),
               np.ascontiguousarray(_FI, np.float32), np.float32(_R), np.float32(_INV_R))
except Exception:  # noqa: BLE001 - any failure means "use numpy's calls"
    _TABLES = None

_MASK64 = (1 << 64) - 1
#: PCG64's 128-bit multiplier (O'Neill's PCG_DEFAULT_MULTIPLIER_128), high and low words.
_MUL_HI = np.uint64(0x2360ED051FC65DA4)
_MUL_LO = np.uint64(0x4385DF649FCCF645)
_c_exp = types.ExternalFunction("exp", types.float64(types.float64))
_c_log1pf = types.ExternalFunction("log1pf", types.float32(types.float32))


@kernel
def _mulhi64(a, b):
    """High 64 bits of the 128-bit product of two uint64."""
    m = np.uint64(0xFFFFFFFF)
    s = np.uint64(32)
    a0, a1, b0, b1 = a & m, a >> s, b & m, b >> s
    p00, p01, p10, p11 = a0 * b0, a0 * b1, a1 * b0, a1 * b1
    mid = (p00 >> s) + (p01 & m) + (p10 & m)
    return p11 + (p01 >> s) + (p10 >> s) + (mid >> s)


@kernel
def _next32(hi, lo, inc_hi, inc_lo, has, buf):
    """One 32-bit draw from a PCG64 state (hi, lo, inc_hi, inc_lo: uint64) with numpy's
    buffered half word (has: 0/1, buf: uint64). Returns (value uint32, hi, lo, has, buf).
    Scalars in and out, so that a loop keeps the state in registers."""
    if has != 0:
        return np.uint32(buf), hi, lo, np.uint64(0), buf
    new_lo = lo * _MUL_LO
    new_hi = _mulhi64(lo, _MUL_LO) + lo * _MUL_HI + hi * _MUL_LO
    lo = new_lo + inc_lo
    hi = new_hi + inc_hi + (np.uint64(1) if lo < new_lo else np.uint64(0))
    x = hi ^ lo
    rot = hi >> np.uint64(58)
    out = (x >> rot) | (x << ((np.uint64(64) - rot) & np.uint64(63)))
    return np.uint32(out & np.uint64(0xFFFFFFFF)), hi, lo, np.uint64(1), out >> np.uint64(32)


@kernel
def _as_float(u):
    """numpy's ``next_float``: the top 24 bits of a 32-bit draw, as a float32 in [0, 1)."""
    return np.float32(u >> np.uint32(8)) * np.float32(1.0 / 16777216.0)


@kernel
def _fill(st, gauss, uniform, ki, wi, fi, r_f, inv_r_f):
    """``gauss`` then ``uniform`` (either may be empty) filled in numpy's order from the state
    ``st`` = [state hi, state lo, inc hi, inc lo, has_uint32, uinteger] (uint64, advanced in
    place). The normal is numpy's ``random_standard_normal_f`` (the float32 ziggurat)."""
    hi, lo, inc_hi, inc_lo, has, buf = st[0], st[1], st[2], st[3], st[4], st[5]
    for i in range(gauss.shape[0]):
        while True:
            r, hi, lo, has, buf = _next32(hi, lo, inc_hi, inc_lo, has, buf)
            idx = r & np.uint32(0xFF)
            rabs = (r >> np.uint32(9)) & np.uint32(0x007FFFFF)
            x = np.float32(rabs) * wi[idx]
            if ((r >> np.uint32(8)) & np.uint32(1)) != 0:
                x = -x
            if rabs < ki[idx]:
                break  # ~99.3 % of draws
            if idx == 0:  # the tail beyond r_f
                while True:
                    u, hi, lo, has, buf = _next32(hi, lo, inc_hi, inc_lo, has, buf)
                    xx = -inv_r_f * _c_log1pf(-_as_float(u))
                    u, hi, lo, has, buf = _next32(hi, lo, inc_hi, inc_lo, has, buf)
                    yy = -_c_log1pf(-_as_float(u))
                    if yy + yy > xx * xx:
                        break
                x = -(r_f + xx) if ((rabs >> np.uint32(8)) & np.uint32(1)) != 0 else r_f + xx
                break
            # a wedge: the comparison in double, as the C expression promotes it
            u, hi, lo, has, buf = _next32(hi, lo, inc_hi, inc_lo, has, buf)
            lhs = (fi[idx - 1] - fi[idx]) * _as_float(u) + fi[idx]
            xd = np.float64(x)
            if np.float64(lhs) < _c_exp(-0.5 * xd * xd):
                break
        gauss[i] = x
    for i in range(uniform.shape[0]):
        u, hi, lo, has, buf = _next32(hi, lo, inc_hi, inc_lo, has, buf)
        uniform[i] = _as_float(u)
    st[0], st[1], st[4], st[5] = hi, lo, has, buf


def _read_state(rng: np.random.Generator) -> np.ndarray | None:
    bg = rng.bit_generator
    if type(bg) is not np.random.PCG64:
        return None
    s = bg.state
    state, inc = int(s["state"]["state"]), int(s["state"]["inc"])
    return np.array([state >> 64, state & _MASK64, inc >> 64, inc & _MASK64, int(s["has_uint32"]),
                     int(s["uinteger"])], np.uint64)


def _write_state(rng: np.random.Generator, st: np.ndarray) -> None:
    hi, lo, ihi, ilo, has, uint = (int(v) for v in st)
    rng.bit_generator.state = {"bit_generator": "PCG64", "state": {"state": (hi << 64) | lo, "inc": (ihi << 64) | ilo},
                               "has_uint32": has, "uinteger": uint}


def _compiled(rng: np.random.Generator, n_gauss: int, n_uniform: int) -> tuple[np.ndarray, np.ndarray] | None:
    st = _read_state(rng)
    if st is None:
        return None
    gauss = np.empty(n_gauss, np.float32)
    uniform = np.empty(n_uniform, np.float32)
    _fill(st, gauss, uniform, *_TABLES)
    _write_state(rng, st)
    return gauss, uniform


_checked: bool | None = None
_check_lock = threading.Lock()


def compiled_draws_available() -> bool:
    """Whether the compiled draws give numpy's values here (checked once per process against
    numpy on two seeds, 400k normals and uniforms each, and the generators' states after)."""
    global _checked
    if _checked is None:
        with _check_lock:
            if _checked is None:
                _checked = _self_check()
    return _checked


def _self_check() -> bool:
    if _TABLES is None:
        return False
    try:
        for seed in (0, 20261127):
            ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
            ref.random(3, dtype=np.float32)  # an odd count: the buffered half word is used
            ours.random(3, dtype=np.float32)
            g, u = _compiled(ours, 400_000, 400_000)
            if not (np.array_equal(g.view(np.uint32), ref.standard_normal(400_000, dtype=np.float32).view(np.uint32))
                    and np.array_equal(u, ref.random(400_000, dtype=np.float32))
                    and ours.bit_generator.state == ref.bit_generator.state):
                return False
        return True
    except Exception:  # noqa: BLE001 - a binding that cannot run means "use numpy's calls"
        return False


def draw_f32(rng: np.random.Generator, n_gauss: int, n_uniform: int) -> tuple[np.ndarray, np.ndarray]:
    """``rng.standard_normal(n_gauss, dtype=np.float32)``, then ``rng.random(n_uniform,
    dtype=np.float32)``: the same values, and ``rng`` left in the same state (see the module
    docstring); (n_gauss,) and (n_uniform,) float32."""
    if n_gauss + n_uniform > 0 and compiled_draws_available():
        out = _compiled(rng, n_gauss, n_uniform)
        if out is not None:
            return out
    return rng.standard_normal(n_gauss, dtype=np.float32), rng.random(n_uniform, dtype=np.float32)
