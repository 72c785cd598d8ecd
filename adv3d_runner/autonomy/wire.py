"""The wire protocol between adv3d and a stack in its own process (docs/stack_protocol.md).

Self-contained on purpose: it imports only the standard library, numpy and msgpack, so a stack
in another environment (other numpy, other Python packages) can copy this one file and serve
with :func:`serve_messages`. adv3d's side is :mod:`adv3d_runner.autonomy.remote`.

A message is a 4-byte big-endian length followed by that many bytes of one msgpack map. An
array is the map ``{"dtype": "<f4", "shape": [P, 4], "data": <bytes>}`` (C order, little
endian): a 130k-point frame travels as one 2 MB byte string, no per-point encoding.
"""
from __future__ import annotations

import struct
from typing import Any, BinaryIO, Callable

import msgpack
import numpy as np

#: The protocol's version: a stack answers ``hello`` with the one it speaks.
PROTOCOL_VERSION = 1
#: Largest message either side accepts (a frame of 130k points is about 2 MB).
MAX_MESSAGE_BYTES = 256 * 2**20
_HEADER = struct.Struct(">I")
_ARRAY_KEYS = {"dtype", "shape", "data"}
_DTYPES = {"<f4", "<f8", "<i1", "<i4", "<i8", "|b1", "|i1", "<u1", "|u1"}


class ProtocolError(ValueError):
    """A message that does not follow the protocol (size, encoding, array fields)."""


def pack_array(a: np.ndarray) -> dict:
    a = np.asarray(a)
    if a.dtype == bool:
        a = a.astype(np.uint8)
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<")) if a.dtype.byteorder == ">" else a)
    data = memoryview(a).cast("B") if a.size else b""  # packed without a copy (a view of no bytes cannot be cast)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": data}


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return pack_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _object_hook(m: dict) -> Any:
    if len(m) == 3 and set(m) == _ARRAY_KEYS:
        dtype, shape, data = m["dtype"], m["shape"], m["data"]
        if dtype not in _DTYPES or not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
            raise ProtocolError(f"bad array header: dtype {dtype!r}, shape {shape!r}")
        dt = np.dtype(dtype)
        if not isinstance(data, bytes) or len(data) != dt.itemsize * int(np.prod(shape, dtype=np.int64)):
            raise ProtocolError(f"array data of {len(data) if isinstance(data, bytes) else '?'} bytes does not "
                                f"fit dtype {dtype} and shape {shape}")
        return np.frombuffer(data, dt).reshape(shape)
    return m


def encode_parts(message: dict) -> tuple[bytes, bytes]:
    """(header, body) of one message: written one after the other (no copy of a large body)."""
    body = msgpack.packb(message, default=_default, use_bin_type=True)
    if len(body) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {len(body)} bytes is over the limit ({MAX_MESSAGE_BYTES})")
    return _HEADER.pack(len(body)), body


def encode(message: dict) -> bytes:
    """One framed message (header + msgpack)."""
    return b"".join(encode_parts(message))


def decode(body: bytes) -> dict:
    """A message body (without its header) -> the map, arrays as numpy arrays (read-only)."""
    try:
        msg = msgpack.unpackb(body, object_hook=_object_hook, raw=False, strict_map_key=False)
    except ProtocolError:
        raise
    except Exception as exc:  # noqa: BLE001 - msgpack's own errors, named
        raise ProtocolError(f"not msgpack: {exc}") from None
    if not isinstance(msg, dict) or not isinstance(msg.get("type"), str):
        raise ProtocolError(f"a message must be a map with a string 'type', got {type(msg).__name__}")
    return msg


def read_exact(stream: BinaryIO, n: int) -> bytes:
    """``n`` bytes from ``stream``; EOFError if it ends before."""
    chunks, got = [], 0
    while got < n:
        chunk = stream.read(n - got)
        if not chunk:
            raise EOFError(f"the stream ended after {got} of {n} bytes")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def read_message(stream: BinaryIO) -> dict:
    (size,) = _HEADER.unpack(read_exact(stream, _HEADER.size))
    if size > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message of {size} bytes announced, over the limit ({MAX_MESSAGE_BYTES})")
    return decode(read_exact(stream, size))


def write_message(stream: BinaryIO, message: dict) -> None:
    data = memoryview(encode(message))
    while len(data):
        n = stream.write(data)  # a raw stream may take part of it
        data = data[len(data) if n is None else n:]
    stream.flush()


def serve_messages(handle: Callable[[dict], dict | None], stream_in: BinaryIO, stream_out: BinaryIO) -> None:
    """The reference server loop: read a message, answer ``handle(message)`` (None: no answer),
    until ``close`` or the end of the input. ``hello`` must be answered with this module's
    :data:`PROTOCOL_VERSION`; an exception in ``handle`` is answered as an ``error`` message."""
    while True:
        try:
            msg = read_message(stream_in)
        except EOFError:
            return
        if msg["type"] == "close":
            return
        try:
            answer = handle(msg)
        except Exception as exc:  # noqa: BLE001 - reported to the runner, which fails the query
            answer = {"type": "error", "message": f"{type(exc).__name__}: {exc}"}
        if answer is not None:
            write_message(stream_out, answer)
