"""A method's state (its temporal history) as compact bytes, for mirroring a session to a store and back.

Layout: ``MAGIC``, a 4-byte little-endian header length, a JSON header (per tensor: name, original dtype, shape,
stored dtype, encoding, byte count), then each tensor's bytes in header order. With ``precision="half"`` a float
tensor is stored as float16 when every value is finite and within float16's range, and as it is otherwise; the
previous frame's geometry (``GEOMETRY``: depth, normals, jitter) stays float32 whatever the precision, since methods
test it against thresholds and a rounded depth would flip where history is valid. Bool tensors are bit-packed. A
payload is zlib-compressed (level 1) when a 4 kB probe of it saves at least three quarters (masks, counters,
constant planes); float planes, which save little for their zlib time, are left raw, and a ``CompressionMemo``
carried between one stream's encodes skips the probe for a plane that did not compress last time (probed again
after ``reprobe_every`` encodes). Decoding gives every tensor back with its original dtype and shape; bytes that are
not a state this module wrote raise ``StateFormatError`` naming what is wrong.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Mapping

import numpy as np
import torch

__all__ = ["PRECISIONS", "CompressionMemo", "StateFormatError", "decode_state", "encode_state"]

MAGIC = b"DNSTATE1"
PRECISIONS = ("half", "float")
GEOMETRY = frozenset({"depth", "normal", "jitter"})  # the state names every method keeps its frame's geometry under
FLOAT16_MAX = 65504.0
_COMPRESS_LEVEL = 1  # speed over ratio: the mirror is written every frame
_MIN_SAVING = 0.75
_PROBE_BYTES = 1 << 12  # zlib level 1 runs at 45-100 MB/s on noise-like floats here: probes must be small

_TORCH_DTYPES = {str(dtype).removeprefix("torch."): dtype for dtype in (
    torch.float64, torch.float32, torch.float16, torch.bfloat16, torch.int64, torch.int32, torch.int16,
    torch.int8, torch.uint8, torch.bool)}


class StateFormatError(ValueError):
    """The bytes are not a state ``encode_state`` wrote (or they were cut short)."""


class CompressionMemo:
    """Whether each tensor of one stream's state compressed when last tried, for that stream's next encodes.

    Not thread-safe: one stream's encodes run one at a time (a session's mirror writer)."""

    def __init__(self, reprobe_every: int = 16) -> None:
        if reprobe_every < 1:
            raise ValueError(f"reprobe_every must be at least 1, got {reprobe_every}")
        self.reprobe_every = reprobe_every
        self._decisions: dict[tuple, list] = {}  # key -> [compressed, encodes left before the next probe]

    def planned(self, key: tuple) -> bool | None:
        """The remembered decision for ``key``, or None when it must be probed (unknown, or due again)."""
        entry = self._decisions.get(key)
        if entry is None or entry[1] <= 0:
            return None
        entry[1] -= 1
        return entry[0]

    def record(self, key: tuple, compressed: bool) -> None:
        self._decisions[key] = [compressed, self.reprobe_every]


def encode_state(state: Mapping[str, torch.Tensor] | None, precision: str = "half",
                 memo: CompressionMemo | None = None) -> bytes:
    """State tensors -> bytes (empty for no history); see the module notes for ``precision`` and ``memo``."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if state is None:
        return b""
    entries, payloads = [], []
    for name, tensor in state.items():
        if not isinstance(tensor, torch.Tensor):
            raise TypeError(f"state entry {name!r} is a {type(tensor).__name__}, not a tensor")
        dtype = str(tensor.dtype).removeprefix("torch.")
        if dtype not in _TORCH_DTYPES:
            raise TypeError(f"state entry {name!r} has dtype {dtype}, which cannot be stored")
        stored, raw = _stored_bytes(tensor.detach().to("cpu"), "float" if name in GEOMETRY else precision)
        raw, encoding = _compressed(raw, (name, stored, len(raw)), memo)
        entries.append({"name": name, "dtype": dtype, "shape": list(tensor.shape), "stored": stored,
                        "encoding": encoding, "bytes": len(raw)})
        payloads.append(raw)
    header = json.dumps({"tensors": entries}).encode()
    return b"".join([MAGIC, struct.pack("<I", len(header)), header, *payloads])


def _compressed(raw: bytes, key: tuple, memo: CompressionMemo | None) -> tuple[bytes, str]:
    """(payload, encoding): zlib where it saves ``_MIN_SAVING``, raw otherwise."""
    planned = memo.planned(key) if memo is not None else None
    if planned is False or not raw:
        return raw, "raw"
    if planned is None and not _worth_compressing(raw):
        if memo is not None:
            memo.record(key, False)
        return raw, "raw"
    packed = zlib.compress(raw, _COMPRESS_LEVEL)
    compressed = len(packed) <= (1 - _MIN_SAVING) * len(raw)
    if memo is not None:
        memo.record(key, compressed)
    return (packed, "zlib") if compressed else (raw, "raw")


def _worth_compressing(raw: bytes) -> bool:
    """Whether a probe of the first ``_PROBE_BYTES`` compresses by ``_MIN_SAVING``: compressing a whole 1080p
    float plane only to throw the result away is slow, and so is a large probe of every tensor every frame."""
    if len(raw) <= _PROBE_BYTES:
        return True
    probe = raw[:_PROBE_BYTES]
    return len(zlib.compress(probe, _COMPRESS_LEVEL)) <= (1 - _MIN_SAVING) * len(probe)


def _stored_bytes(tensor: torch.Tensor, precision: str) -> tuple[str, bytes]:
    if tensor.dtype == torch.bool:
        return "bits", np.packbits(tensor.numpy().reshape(-1)).tobytes()
    if tensor.dtype == torch.bfloat16:  # numpy has no bfloat16: its bits as int16
        return "bfloat16", tensor.contiguous().view(torch.int16).numpy().tobytes()
    if precision == "half" and tensor.is_floating_point() and tensor.dtype != torch.float16 and tensor.numel():
        # torch, not numpy: both passes use every thread. max |x| is NaN if any value is, and inf if any is.
        peak = float(tensor.abs().amax())
        if peak <= FLOAT16_MAX:
            return "float16", tensor.to(torch.float16).contiguous().numpy().tobytes()
    array = tensor.contiguous().numpy()
    return str(array.dtype), array.tobytes()


def decode_state(data: bytes | None, device: torch.device | str = "cpu") -> dict[str, torch.Tensor] | None:
    """Bytes from ``encode_state`` -> the state (each tensor with its original dtype and shape) on ``device``."""
    if not data:
        return None
    view = memoryview(data)
    if bytes(view[:len(MAGIC)]) != MAGIC:
        raise StateFormatError("not a stored session state (its first bytes are not the state format's marker)")
    try:
        (length,) = struct.unpack_from("<I", view, len(MAGIC))
        start = len(MAGIC) + 4
        entries = json.loads(bytes(view[start:start + length]))["tensors"]
        offset = start + length
        state = {}
        for entry in entries:
            chunk = view[offset:offset + entry["bytes"]]
            if len(chunk) != entry["bytes"]:
                raise StateFormatError(f"state entry {entry['name']!r} is cut short ({len(chunk)} of "
                                       f"{entry['bytes']} bytes)")
            offset += entry["bytes"]
            raw = zlib.decompress(chunk) if entry["encoding"] == "zlib" else bytes(chunk)
            state[entry["name"]] = _tensor(raw, entry).to(device)
    except StateFormatError:
        raise
    except (KeyError, TypeError, ValueError, struct.error, zlib.error) as error:
        raise StateFormatError(f"stored session state is damaged: {error}") from None
    if offset != len(data):
        raise StateFormatError(f"stored session state has {len(data) - offset} bytes after its last tensor")
    return state


def _tensor(raw: bytes, entry: dict) -> torch.Tensor:
    shape, dtype, stored = tuple(entry["shape"]), _TORCH_DTYPES[entry["dtype"]], entry["stored"]
    count = int(np.prod(shape, dtype=np.int64))
    if stored == "bits":
        if len(raw) * 8 < count:
            raise StateFormatError(f"state entry {entry['name']!r} holds {len(raw) * 8} bits for shape {list(shape)}")
        bits = np.unpackbits(np.frombuffer(raw, dtype=np.uint8), count=count)
        return torch.from_numpy(bits.astype(bool)).reshape(shape)
    if stored == "bfloat16":
        return torch.from_numpy(np.frombuffer(raw, dtype=np.int16).copy()).view(torch.bfloat16).reshape(shape)
    array = np.frombuffer(raw, dtype=np.dtype(stored))
    if array.size != count:
        raise StateFormatError(f"state entry {entry['name']!r} holds {array.size} values for shape {list(shape)}")
    return torch.from_numpy(array.copy()).reshape(shape).to(dtype)
