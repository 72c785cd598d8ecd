"""Matrix products with one fixed, machine-independent rounding: fused multiply-adds in order.

Why (the library rebuild, ``assets/vehicles/build_library.sh``): numpy hands ``np.dot`` and
``@`` of float64 matrices to OpenBLAS, which picks its kernel by the CPU it finds at start-up.
The kernels of every x86-64 CPU since Haswell (Haswell, SkylakeX, Zen, SapphireRapids, ...)
accumulate each dot product with fused multiply-adds, ``acc = fma(a_k, b_k, acc)`` for k in
order; the SSE kernels (Prescott, Nehalem, Sandybridge) round every product and every sum. A
CPU that numpy's OpenBLAS (0.3.23 in numpy 1.26.4) does not know, such as an Emerald Rapids
Xeon (family 6, model 207), falls back to Prescott even though it has FMA and AVX-512. The
node transforms of a glTF scene then come out an ulp or two apart, and so do the vertex
positions of a library mesh (2026-11-27: ``openmaterial-examples/coupe.glb``, the shipped one
built on an FMA kernel, came out with two float32 coordinates 1.1e-16 m different on the
Prescott kernel; no other file changed). The shipped library was built with FMA kernels.

:func:`dot` computes exactly what those FMA kernels compute (checked bit for bit against
OpenBLAS's Haswell, SkylakeX, Zen and SapphireRapids kernels, ``tests/test_mesh_io.py``) on
any CPU: :func:`fma` is a correctly rounded fused multiply-add built from ordinary float64
operations (Boldo and Melquiond, "Emulation of FMA and correctly rounded sums: proved
algorithms using rounding to odd", IEEE Trans. Computers 57(4), 2008), so it needs neither FMA
hardware nor a compiler. Valid away from overflow and underflow (|products| well inside
1e-290 .. 1e290), which is where vehicle coordinates and transforms live.
"""
from __future__ import annotations

import numpy as np

_SPLITTER = 134217729.0  # 2**27 + 1 (Veltkamp's split of a float64 into two 26-bit halves)


def _two_sum(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s, e) with s = fl(a + b) and s + e = a + b exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


def _split(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = _SPLITTER * a
    hi = c - (c - a)
    return hi, a - hi


def _two_product(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p, e) with p = fl(a * b) and p + e = a * b exactly (Dekker)."""
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _add_round_to_odd(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x + y rounded to odd: exact sums as they are, inexact ones to the neighbour with an odd
    last mantissa bit."""
    s, e = _two_sum(x, y)
    # s is round-to-nearest; when inexact and even, the odd neighbour lies towards the exact sum
    move = (e != 0) & ((s.view(np.int64) & 1) == 0)
    if np.any(move):
        s = np.where(move, np.nextafter(s, np.where(e > 0, np.inf, -np.inf)), s)
    return s


def fma(a, b, c) -> np.ndarray:
    """a * b + c with one rounding (round to nearest even), element-wise, as float64."""
    a, b, c = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (a, b, c)))
    uh, ul = _two_product(a, b)
    th, tl = _two_sum(c, uh)
    return th + _add_round_to_odd(tl, ul)


def dot(a, b) -> np.ndarray:
    """``a @ b`` of 2-D float64 arrays as an FMA BLAS kernel computes it: for each element,
    ``acc = a[i, 0] * b[0, j]``, then ``acc = fma(a[i, k], b[k, j], acc)`` for k = 1, 2, ...,
    and the kernel's final ``0 + acc`` (so a zero is +0.0)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[0] or a.shape[1] == 0:
        raise ValueError(f"dot needs (m, k) and (k, n) arrays with k > 0 (got {a.shape} and {b.shape})")
    acc = a[:, :1] * b[:1, :]
    for k in range(1, a.shape[1]):
        acc = fma(a[:, k:k + 1], b[k:k + 1, :], acc)
    return acc + 0.0


def chain(matrices) -> np.ndarray:
    """Product of square matrices as ``np.linalg.multi_dot`` orders it for equal shapes,
    ``m0 @ (m1 @ (m2 @ ...))``, each product by :func:`dot`."""
    matrices = [np.asarray(m, dtype=np.float64) for m in matrices]
    if not matrices:
        raise ValueError("chain needs at least one matrix")
    out = matrices[-1]
    for m in reversed(matrices[:-1]):
        out = dot(m, out)
    return out


def transform_points(points, matrix) -> np.ndarray:
    """(n, 3) points through a (4, 4) homogeneous matrix as ``trimesh.transform_points`` does
    (``matrix @ [p, 1]``; a matrix within 1e-8 of the identity leaves the points as they are),
    each product by :func:`dot`."""
    points = np.asarray(points, dtype=np.float64)
    matrix = np.asarray(matrix, dtype=np.float64)
    if len(points) == 0 or np.abs(matrix - np.eye(4)).max() < 1e-8:
        return np.ascontiguousarray(points.copy())
    stack = np.column_stack((points, np.ones(len(points))))
    return np.ascontiguousarray(dot(matrix, stack.T).T[:, :3])
