"""Direct binding to the Embree 4 library that ``embreex`` bundles: scenes and packet casts.

Why: ``embreex``'s ``EmbreeScene.run`` casts one ray per ``rtcIntersect1`` call from a Cython
loop and allocates five output arrays (u, v, Ng, primID, geomID) per call. Here the same
library is called from a compiled loop (:mod:`adv3d_runner.jit`) that fills Embree's SOA ray
packets of :data:`PACKET` rays and calls ``rtcIntersect8``; only the hit distance (``tfar``, in
place) and the face index come back. A frame's HDL-64E background cast (about 117k rays on the
7970-triangle highway background, ``bench/lidar.py --ratio``) takes 8.8 ms of CPU instead of
13.1 on this project's machine (one core, AVX-512 Xeon). On all 133k rays alone, packets of 8
took 9.6 ms, of 4 10.0, of 16 12.0, single rays from the same loop 13.3 and embreex 13.9, so 8
it is (docs/lidar.md, "Direct Embree binding").

Same bits: a scene is built as ``embreex`` builds its own (one triangle geometry, default
build quality, ``RTC_SCENE_FLAG_ROBUST``: without that flag 23 % of an HDL-64E frame's hit
distances on the background differ, by an ulp) and each ray is set up as ``embreex`` sets it (tnear 0, time 0, mask all
ones, ids invalid), so the distances and faces are those of ``EmbreeScene.run(..., output=1)``
bit for bit (``tests/test_raycast.py`` checks it on the background and on actor meshes, with
misses, edge- and vertex-grazing rays and partial packets).

The coherent query (``intersect(..., coherent=True)``, ``RTC_RAY_QUERY_FLAG_COHERENT``) is cast
in packets of :data:`COHERENT_PACKET` (16) with ``rtcIntersect16``: its frustum traversal
gains from wider packets. It may resolve near-ties between faces differently from the
reference query; :mod:`adv3d_runner.sensors.coherent` makes its results exact.

The library is the one ``embreex`` loaded (the file next to the installed package, found in
the process's mapped files where the platform lists them): scenes made here and
:class:`~adv3d_runner.sensors.raycast.MeshBVH`'s fallback share the library, its version and
its TBB pool. The compiled loop calls ``rtcIntersect8`` by name (``numba.types.ExternalFunction``
after ``llvmlite.binding.load_library_permanently``), so it is cached on disk like every other
kernel (0.8 s to compile once; then about 0.2 s to load with numba's start-up). Where the library is not found (another wheel layout, another Embree major version),
:func:`available` is False, :func:`unavailable_reason` says why and ``MeshBVH`` falls back to
``embreex``'s ``run``.
"""
from __future__ import annotations

import ctypes
import importlib.util
import sys
import threading
from pathlib import Path

import numpy as np
from numba import types

from ..jit import kernel
from ..machine import embree_isa

__all__ = ["PACKET", "TriangleScene", "available", "library_path", "unavailable_reason"]

#: Rays per ``rtcIntersectN`` call (the fastest on this project's machine, see the docstring).
PACKET = 8

# Embree 4 API constants (include/embree4/rtcore_*.h).
_RTC_SCENE_FLAG_ROBUST = 1 << 2
_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_BUFFER_TYPE_INDEX = 0
_RTC_BUFFER_TYPE_VERTEX = 1
_RTC_FORMAT_UINT3 = 0x5003
_RTC_FORMAT_FLOAT3 = 0x9003
_RTC_DEVICE_PROPERTY_VERSION_MAJOR = 1

# RTCRayHitN (SOA, N lanes of each field, 32/64-byte aligned): the ray's 12 fields (org_x, org_y,
# org_z, tnear, dir_x, dir_y, dir_z, time, tfar, mask, id, flags), then the hit's (Ng_x, Ng_y,
# Ng_z, u, v, primID, geomID, instID[1], instPrimID[1] where the library has instance arrays).
# Field indices; a field's lanes start at index x N words. The valid mask (N int32) lies after
# the largest hit layout.
_TFAR, _MASK, _ID, _FLAGS, _U, _V, _PRIM, _GEOM, _INST, _VALID = 8, 9, 10, 11, 15, 16, 17, 18, 19, 24
#: The coherent query's packet width: its frustum traversal gains from wider packets (a
#: highway frame's background: 3.5 ms in packets of 8, 2.9 of 16; ``bench/lidar.py
#: --coherent``), unlike the reference query's (9.6 ms of 8, 12.0 of 16; docs/lidar.md).
COHERENT_PACKET = 16
_WIDEST = 16
_WORDS = (_VALID + 1) * _WIDEST
_ALIGN = 64  # bytes: enough for any packet width
# RTCIntersectArguments (flags, feature mask, context, filter, intersect; 32 bytes), after the
# packet: 16 words leave room for the optional min-width field of other builds.
_ARGS_WORDS = 16
#: ``RTC_RAY_QUERY_FLAG_COHERENT`` (include/embree4/rtcore_common.h).
COHERENT = 1 << 16

#: ``void rtcIntersectN(const int* valid, RTCScene scene, RTCRayHitN* rayhit,
#: RTCIntersectArguments* args)``, pointers passed as integers.
_rtc_intersect8 = types.ExternalFunction("rtcIntersect8", types.void(types.intp, types.intp, types.intp, types.intp))
_rtc_intersect16 = types.ExternalFunction("rtcIntersect16", types.void(types.intp, types.intp, types.intp, types.intp))


@kernel
def _cast(scene, origins, dirs, tfar, prim, uv, flags, width):
    """Cast rays ``dirs`` ((N, 3) float32) from ``origins`` ((1, 3): one for all, or (N, 3))
    against ``scene`` (an RTCScene pointer) in packets of ``width`` (8 or 16) rays; ``tfar``
    ((N,) float32) is the limit per ray and takes the hit distance in place; ``prim`` ((N,)
    int32) receives the face hit (-1: none); ``uv`` ((N, 2) float32, or (0, 2) for none) the
    hit's barycentric u, v. ``flags``: ``RTCRayQueryFlags`` (0: Embree's default query, no
    arguments passed)."""
    n = dirs.shape[0]
    w = 16 if width == 16 else 8
    raw = np.zeros(_WORDS + _ARGS_WORDS + _ALIGN // 4, np.int32)
    start = ((_ALIGN - raw.ctypes.data % _ALIGN) % _ALIGN) // 4
    ib = raw[start:start + _WORDS + _ARGS_WORDS]
    fb = ib.view(np.float32)
    addr = ib.ctypes.data
    valid = addr + 4 * _VALID * w
    args = 0
    if flags != 0:  # RTCIntersectArguments: flags, feature mask (all), null context and callbacks
        ib[_WORDS] = flags
        ib[_WORDS + 1] = -1
        args = addr + 4 * _WORDS
    want_uv = uv.shape[0] > 0
    one = origins.shape[0] == 1
    for s in range(0, n, w):
        m = min(w, n - s)
        for j in range(w):
            if j < m:
                i = s + j
                r = 0 if one else i
                fb[j] = origins[r, 0]
                fb[w + j] = origins[r, 1]
                fb[2 * w + j] = origins[r, 2]
                fb[3 * w + j] = 0.0  # tnear
                fb[4 * w + j] = dirs[i, 0]
                fb[5 * w + j] = dirs[i, 1]
                fb[6 * w + j] = dirs[i, 2]
                fb[7 * w + j] = 0.0  # time
                fb[_TFAR * w + j] = tfar[i]
                ib[_MASK * w + j] = -1
                ib[_ID * w + j] = 0
                ib[_FLAGS * w + j] = 0
                ib[_PRIM * w + j] = -1  # RTC_INVALID_GEOMETRY_ID
                ib[_GEOM * w + j] = -1
                ib[_INST * w + j] = -1
                ib[_VALID * w + j] = -1
            else:
                ib[_VALID * w + j] = 0  # an inactive lane: its results are neither written nor read
        if w == 16:
            _rtc_intersect16(valid, scene, addr, args)
        else:
            _rtc_intersect8(valid, scene, addr, args)
        for j in range(m):
            tfar[s + j] = fb[_TFAR * w + j]  # unchanged on a miss
            prim[s + j] = ib[_PRIM * w + j]
            if want_uv:
                uv[s + j, 0] = fb[_U * w + j]
                uv[s + j, 1] = fb[_V * w + j]


_NO_UV = np.zeros((0, 2), np.float32)


class _Embree:
    """The loaded library: ctypes functions for scene building, and the process's device."""

    def __init__(self, path: Path):
        import llvmlite.binding as llvm

        self.path = path
        lib = ctypes.CDLL(str(path))
        vp, u, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t

        def fn(name, args, res):
            f = getattr(lib, name)
            f.argtypes, f.restype = args, res
            return f

        self.new_device = fn("rtcNewDevice", [ctypes.c_char_p], vp)
        self.device_property = fn("rtcGetDeviceProperty", [vp, ctypes.c_int], ctypes.c_ssize_t)
        self.device_error = fn("rtcGetDeviceError", [vp], ctypes.c_int)
        self.new_scene = fn("rtcNewScene", [vp], vp)
        self.set_scene_flags = fn("rtcSetSceneFlags", [vp, ctypes.c_int], None)
        self.new_geometry = fn("rtcNewGeometry", [vp, ctypes.c_int], vp)
        self.set_shared_buffer = fn("rtcSetSharedGeometryBuffer", [vp, ctypes.c_int, u, ctypes.c_int, vp, sz, sz, sz],
                                    None)
        self.commit_geometry = fn("rtcCommitGeometry", [vp], None)
        self.attach_geometry = fn("rtcAttachGeometry", [vp, vp], u)
        self.release_geometry = fn("rtcReleaseGeometry", [vp], None)
        self.commit_scene = fn("rtcCommitScene", [vp], None)
        self.release_scene = fn("rtcReleaseScene", [vp], None)
        getattr(lib, "rtcIntersect8"), getattr(lib, "rtcIntersect16")  # the kernel's symbols, before it links
        # The ISA is pinned (machine.embree_isa): Embree's kernels, and so the last bits of
        # some hits, depend on it (docs/reliability.md).
        self.isa = embree_isa()
        self.device = self.new_device(f"isa={self.isa}".encode() if self.isa else None)
        if not self.device:
            raise OSError(f"rtcNewDevice failed (error {self.device_error(None)})")
        major = self.device_property(self.device, _RTC_DEVICE_PROPERTY_VERSION_MAJOR)
        if major != 4:
            raise OSError(f"Embree {major}, not 4 (the packet layout here is Embree 4's)")
        # The kernel finds rtcIntersect8 by name among the permanently loaded libraries.
        llvm.load_library_permanently(str(path))

    def check(self, what: str) -> None:
        code = self.device_error(self.device)
        if code:
            raise RuntimeError(f"Embree error {code} while {what}")


_STATE: dict = {}
_LOCK = threading.Lock()


def _library_candidates() -> list[Path]:
    """Embree 4 libraries shipped with the installed embreex: the one its extension has loaded
    first (Linux: ``/proc/self/maps``), then the wheel layouts' folders, sorted."""
    spec = importlib.util.find_spec("embreex")
    if spec is None or not spec.submodule_search_locations:
        return []
    pkg = Path(next(iter(spec.submodule_search_locations)))
    found = []
    for folder, pattern in ((pkg.parent / "embreex.libs", "libembree4*.so*"),  # auditwheel (Linux)
                            (pkg / ".dylibs", "libembree4*.dylib"),  # delocate (macOS)
                            (pkg.parent / "embreex.libs", "embree4*.dll"),  # delvewheel (Windows)
                            (pkg, "*embree4*.so*"), (pkg, "*embree4*.dylib"), (pkg, "*embree4*.dll")):
        found += sorted(p for p in folder.glob(pattern) if p.is_file())
    maps = Path("/proc/self/maps")
    if found and maps.exists():
        import embreex.rtcore  # noqa: F401  (loads the library)

        mapped = {line.split(None, 5)[-1].strip() for line in maps.read_text().splitlines()
                  if "embree4" in line and "/" in line}
        found.sort(key=lambda p: str(p.resolve()) not in mapped and str(p) not in mapped)
    return found


def _load() -> _Embree | None:
    if "lib" not in _STATE:
        with _LOCK:
            if "lib" not in _STATE:
                _STATE.update(_open())
    return _STATE["lib"]


def _open() -> dict:
    """{"lib": the loaded library or None, "reason": why it is None}."""
    embree_isa()  # a bad ADV3D_EMBREE_ISA is the user's error, never a silent fallback
    if sys.maxsize <= 2 ** 32:
        return {"lib": None, "reason": "a 32-bit Python (pointers are passed as 64-bit integers)"}
    try:
        candidates = _library_candidates()
    except Exception as exc:  # noqa: BLE001 - any failure means: use embreex
        return {"lib": None, "reason": f"looking for embreex's Embree library failed: {exc!r}"}
    if not candidates:
        return {"lib": None, "reason": "no Embree 4 library found next to the installed embreex"}
    try:
        return {"lib": _Embree(candidates[0]), "reason": None}
    except Exception as exc:  # noqa: BLE001
        return {"lib": None, "reason": f"{candidates[0]}: {exc!r}"}


def available() -> bool:
    """Whether the direct binding can be used (the library is loaded on the first call)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (None when it is True)."""
    _load()
    return _STATE["reason"]


def isa() -> str | None:
    """The ISA the binding's Embree device runs (:func:`adv3d_runner.machine.embree_isa`; None:
    Embree's own choice, or the binding is unavailable)."""
    lib = _load()
    return None if lib is None else lib.isa


def coherent_packet() -> int:
    """Rays per coherent call: 16 (``rtcIntersect16``) where Embree runs AVX-512, else 8 (with
    AVX2 kernels a packet of 16 costs 3x one of 8: 11.3 against 3.6 ms for a background frame)."""
    return COHERENT_PACKET if isa() == "avx512" else PACKET


def coherent_pays() -> bool:
    """Whether coherent casts (:mod:`~adv3d_runner.sensors.coherent`) are faster than plain
    ones here: with AVX-512 and AVX2 kernels, not with SSE4.2 ones. HDL-64E background frame of
    ``highway-benchmark-000000``, certified coherent cast against the reference query, on an AMD
    EPYC (Zen 4): AVX-512 4.1 against 8.0 ms, AVX2 (packets of 8) 5.3 against 8.0, SSE4.2 15.8
    against 13.6 (``ADV3D_EMBREE_ISA=... bench/lidar.py --coherent 3``,
    ``bench/results/lidar_coherent.epyc-*.json``; docs/lidar.md). The hits are the same either way."""
    return isa() in ("avx512", "avx2")


def library_path() -> Path | None:
    """The Embree library file in use (None when unavailable)."""
    lib = _load()
    return None if lib is None else lib.path


class TriangleScene:
    """A committed, robust Embree scene over one triangle mesh.

    Args:
        vertices: (V, 3) float32 C-contiguous vertex positions.
        faces: (F, 3) int32 C-contiguous vertex indices (0 <= index < V; checked by the caller),
            F >= 1.
        robust: ``RTC_SCENE_FLAG_ROBUST`` (as ``embreex``'s scenes; False only to show, in the
            tests, that the flag changes distances).

    Embree reads both arrays where they lie (shared buffers): padded copies are kept on the
    object for its lifetime. The scene is released when the object is collected.

    Raises:
        RuntimeError: the binding is unavailable (:func:`available`) or Embree reports an error.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, robust: bool = True):
        lib = _load()
        if lib is None:
            raise RuntimeError(f"direct Embree binding unavailable: {_STATE['reason']}")
        if vertices.dtype != np.float32 or faces.dtype != np.int32 or vertices.ndim != 2 or faces.ndim != 2:
            raise ValueError("vertices (V, 3) float32 and faces (F, 3) int32 expected")
        nv, nf = len(vertices), len(faces)
        # One spare row each: Embree may read the last item with a 16-byte load.
        self._vertices = np.zeros((nv + 1, 3), np.float32)
        self._vertices[:nv] = vertices
        self._faces = np.zeros((nf + 1, 3), np.int32)
        self._faces[:nf] = faces
        self._lib = lib
        self._scene = None
        scene = lib.new_scene(lib.device)
        if not scene:
            lib.check("creating a scene")
            raise RuntimeError("rtcNewScene failed")
        self._scene = scene
        lib.set_scene_flags(scene, _RTC_SCENE_FLAG_ROBUST if robust else 0)
        geom = lib.new_geometry(lib.device, _RTC_GEOMETRY_TYPE_TRIANGLE)
        if not geom:
            lib.check("creating a triangle geometry")
            raise RuntimeError("rtcNewGeometry failed")
        try:
            lib.set_shared_buffer(geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, self._vertices.ctypes.data, 0,
                                  12, nv)
            lib.set_shared_buffer(geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT3, self._faces.ctypes.data, 0,
                                  12, nf)
            lib.commit_geometry(geom)
            lib.attach_geometry(scene, geom)
        finally:
            lib.release_geometry(geom)  # the scene holds its own reference
        lib.commit_scene(scene)  # builds the BVH now (TBB)
        lib.check("building a scene")

    def intersect(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray,
                  uv: np.ndarray | None = None, coherent: bool = False) -> np.ndarray:
        """Cast rays; ``tfar`` takes the hit distance IN PLACE where a hit is closer.

        Args:
            origins: (1, 3) (one for all rays) or (N, 3) float32 C-contiguous.
            directions: (N, 3) float32 C-contiguous.
            tfar: (N,) float32 C-contiguous limits.
            uv: optional (N, 2) float32 C-contiguous output: the hit's barycentric (u, v)
                (point = (1 - u - v) v0 + u v1 + v v2; unwritten on a miss).
            coherent: pass ``RTC_RAY_QUERY_FLAG_COHERENT`` (Embree's frustum traversal for
                packets of neighbouring rays: about 3x faster on a LiDAR frame, but where two
                faces tie within rounding it may report the other one; see
                :mod:`adv3d_runner.sensors.coherent`, which makes its results exact).

        Returns:
            (N,) int32 face hit, -1 where none is closer than ``tfar``.
        """
        prim = np.empty(len(directions), np.int32)
        _cast(self._scene, origins, directions, tfar, prim, _NO_UV if uv is None else uv,
              COHERENT if coherent else 0, coherent_packet() if coherent else PACKET)
        return prim

    def __reduce__(self):
        raise TypeError("an Embree scene cannot be pickled (it is a pointer into this process)")

    def __del__(self):
        scene, self._scene = getattr(self, "_scene", None), None
        if scene:
            try:
                self._lib.release_scene(scene)
            except Exception:  # noqa: BLE001 - interpreter shutdown
                pass
