"""CUDA graphs for a method's step on a GPU: a replay of captured kernels instead of hundreds of launches per frame.

At a fixed resolution a step launches the same kernels every frame, and on a GPU their launch overhead rather than
their arithmetic bounds a small network. ``with_cuda_graphs`` makes ``method.step`` copy each frame and state into
static buffers and replay graphs captured from its own eager step. The capture is split at the step's OIDN calls
(``intercepted_oidn``): OIDN runs on its own device between the captured parts, on the static tensors the part
before it wrote, and its result goes into a static buffer the next part reads. A structure (shapes, dtypes, which
state entries and optional buffers are present) is captured the second time it is seen (the first runs eagerly,
the warm-up a capture needs) and kept among the ``max_graphs`` most recent, so a new resolution is captured anew.
Small constants the ops make with ``torch.tensor(..., device=)`` are filled on the device during a capture (a
host copy would break it). A frame with a camera cut, tensors off the graphs' device and a structure whose capture
failed run eagerly. Outputs are copies (a later replay never overwrites what a caller kept); one method's graphed
steps run one at a time (one set of static buffers). Off CUDA the method is left as it is. More:
docs/benchmark.md, "CUDA graphs".
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import nn

from model.methods.oidn import intercepted_oidn, oidn_denoise

__all__ = ["CapturedStep", "CudaBackend", "GraphCache", "GraphedStep", "HostCall", "allocate_like",
           "capture_safe_constants", "clone_tensors", "copy_into", "device_constant", "structure_key",
           "with_cuda_graphs"]

log = logging.getLogger(__name__)

MAX_GRAPHS = 2  # captured structures kept per method: the steady state of two resolutions (each holds its memory)
HOST_FIELDS = ("camera_cut",)  # frame fields read on the host (a cut drops history): kept on the CPU in the capture


def structure_key(value: Any) -> Hashable:
    """What a captured graph depends on besides tensor values: every tensor's shape, stride, dtype and device,
    which entries and optional fields are present (None or not) and the plain Python values."""
    if isinstance(value, torch.Tensor):
        return ("tensor", tuple(value.shape), tuple(value.stride()), str(value.dtype), str(value.device))
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if dataclasses.is_dataclass(value):
        return (type(value).__name__, tuple((field.name, structure_key(getattr(value, field.name)))
                                            for field in dataclasses.fields(value)))
    if isinstance(value, dict):
        return ("dict", tuple(sorted((str(name), structure_key(item)) for name, item in value.items())))
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, tuple(structure_key(item) for item in value))
    raise TypeError(f"cannot key a graph on a {type(value).__name__}")


def _map(value: Any, tensor: Callable[[torch.Tensor, str], Any], name: str = "") -> Any:
    if isinstance(value, torch.Tensor):
        return tensor(value, name)
    if dataclasses.is_dataclass(value):
        return dataclasses.replace(value, **{field.name: _map(getattr(value, field.name), tensor, field.name)
                                             for field in dataclasses.fields(value) if field.init})
    if isinstance(value, dict):
        return {key: _map(item, tensor, str(key)) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_map(item, tensor, name) for item in value)
    return value


def _tensors(value: Any, name: str = "") -> Iterator[tuple[str, torch.Tensor]]:
    """(field or entry name, tensor) of every tensor in ``value``."""
    if isinstance(value, torch.Tensor):
        yield name, value
    elif dataclasses.is_dataclass(value):
        for field in dataclasses.fields(value):
            yield from _tensors(getattr(value, field.name), field.name)
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _tensors(item, str(key))
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _tensors(item, name)


def allocate_like(value: Any) -> Any:
    """Static buffers shaped like ``value``'s tensors (strides kept), the rest of ``value`` as it is; a frame's
    ``HOST_FIELDS`` become zeros on the CPU (no cut, read on the host without a device sync)."""
    def buffer(tensor: torch.Tensor, name: str) -> torch.Tensor:
        if name in HOST_FIELDS:
            return torch.zeros(tensor.shape, dtype=tensor.dtype)
        return torch.empty_strided(tensor.shape, tensor.stride(), dtype=tensor.dtype, device=tensor.device)
    return _map(value, buffer)


def copy_into(static: Any, value: Any) -> None:
    """Copy ``value``'s tensors into the static buffers of the same structure (``HOST_FIELDS`` left alone)."""
    if isinstance(static, torch.Tensor):
        static.copy_(value)
    elif dataclasses.is_dataclass(static):
        for field in dataclasses.fields(static):
            if field.name not in HOST_FIELDS:
                copy_into(getattr(static, field.name), getattr(value, field.name))
    elif isinstance(static, dict):
        if static.keys() != value.keys():
            raise ValueError(f"state entries {sorted(value)} do not match the captured {sorted(static)}")
        for key in static:
            copy_into(static[key], value[key])
    elif isinstance(static, (list, tuple)):
        for item, new in zip(static, value, strict=True):
            copy_into(item, new)


def clone_tensors(value: Any) -> Any:
    return _map(value, lambda tensor, _: tensor.clone())


def device_constant(data: Any, dtype: torch.dtype | None, device: torch.device | str) -> torch.Tensor:
    """``torch.tensor(data, dtype=dtype, device=device)`` made by one fill per value on the device: no host-to-device
    copy, which a capture refuses (a copy from pageable memory synchronizes)."""
    return _filled(_REAL_TENSOR(data, dtype=dtype), device)


def _filled(host: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    out = torch.empty(host.shape, dtype=host.dtype, device=device)
    flat = out.view(-1)
    for index, value in enumerate(host.reshape(-1).tolist()):
        flat[index].fill_(value)
    return out


_REAL_TENSOR = torch.tensor
_CONSTANTS = threading.local()
_CONSTANTS_LOCK = threading.Lock()
_CONSTANTS_USERS = [0]
MAX_CONSTANT_VALUES = 64  # larger data keeps torch's copy (and a capture that meets it fails, then runs eagerly)


def _capture_safe_tensor(data: Any, *args: Any, dtype: torch.dtype | None = None, device: Any = None,
                         **kwargs: Any) -> torch.Tensor:
    if (getattr(_CONSTANTS, "capturing", False) and device is not None and not args and not kwargs
            and torch.device(device).type == "cuda" and not isinstance(data, torch.Tensor)):
        try:
            host = _REAL_TENSOR(data, dtype=dtype)
        except (TypeError, ValueError, RuntimeError):  # not plain numbers: torch's own call decides
            host = None
        if host is not None and host.numel() <= MAX_CONSTANT_VALUES:
            return _filled(host, device)
    return _REAL_TENSOR(data, *args, dtype=dtype, device=device, **kwargs)


@contextmanager
def capture_safe_constants() -> Iterator[None]:
    """For the block, this thread's ``torch.tensor(numbers, device=<cuda>)`` calls (the ops make small constants
    so: grid sizes, scale factors, tap offsets) become ``device_constant``; other threads' calls are unchanged."""
    with _CONSTANTS_LOCK:
        _CONSTANTS_USERS[0] += 1
        torch.tensor = _capture_safe_tensor
    _CONSTANTS.capturing = True
    try:
        yield
    finally:
        _CONSTANTS.capturing = False
        with _CONSTANTS_LOCK:
            _CONSTANTS_USERS[0] -= 1
            if not _CONSTANTS_USERS[0]:
                torch.tensor = _REAL_TENSOR


class CudaBackend:
    """torch.cuda's graphs, captured on a side stream, where a structure's warm-up call runs too, as torch asks
    (thread-local capture mode: other threads' work on the device does not break a capture). The side stream
    starts after the work queued on the current one and the current one waits for it at the end."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.stream: torch.cuda.Stream | None = None

    @contextmanager
    def side_stream(self) -> Iterator[None]:
        if self.stream is None:
            self.stream = torch.cuda.Stream(self.device)
        self.stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(self.stream):
            yield
        torch.cuda.current_stream(self.device).wait_stream(self.stream)

    def new_graph(self) -> torch.cuda.CUDAGraph:
        return torch.cuda.CUDAGraph()

    def begin(self, graph: torch.cuda.CUDAGraph, pool: Any) -> Any:
        if pool is None:  # a capture's first part: no earlier work still running, as torch.cuda.graph does
            torch.cuda.synchronize(self.device)
        graph.capture_begin(pool=pool, capture_error_mode="thread_local")
        return graph.pool()

    def end(self, graph: torch.cuda.CUDAGraph) -> None:
        graph.capture_end()

    def replay(self, graph: torch.cuda.CUDAGraph) -> None:
        graph.replay()

    def synchronize(self) -> None:
        """Before an OIDN call reads what a replay wrote. pyoidn runs OIDN on torch's current stream and executes
        synchronously, so the host waits here no longer than it would in OIDN's call; an OIDN on a queue of its own
        would need it."""
        torch.cuda.current_stream(self.device).synchronize()


@dataclasses.dataclass
class HostCall:
    """An OIDN call between two captured parts: its frame (static tensors), quality and result buffer."""

    frame: Any
    quality: str
    result: torch.Tensor

    def run(self) -> None:
        self.result.copy_(oidn_denoise(self.frame, self.quality))


class CapturedStep:
    """One structure's capture: static inputs, the parts (graphs and host calls, in order) and static outputs."""

    def __init__(self, frame: Any, state: Any, parts: list[Any], outputs: Any, backend: Any) -> None:
        self.frame, self.state, self.parts, self.outputs, self.backend = frame, state, parts, outputs, backend

    @classmethod
    def capture(cls, step: Callable[[Any, Any], Any], frame: Any, state: Any, backend: Any) -> tuple[CapturedStep, Any]:
        """Capture ``step`` on static copies of ``frame`` and ``state``; the capture and this frame's outputs."""
        static_frame, static_state = allocate_like(frame), allocate_like(state)
        copy_into(static_frame, frame)
        copy_into(static_state, state)
        parts: list[Any] = []
        with backend.side_stream(), capture_safe_constants():
            graph = backend.new_graph()
            pool = backend.begin(graph, None)

            def host(denoise: Callable[[Any, str], torch.Tensor], oidn_frame: Any, quality: str) -> torch.Tensor:
                nonlocal graph
                backend.end(graph)
                parts.append(graph)
                backend.replay(graph)  # the part so far, for real: OIDN reads what it wrote
                backend.synchronize()
                result = denoise(oidn_frame, quality).clone()
                parts.append(HostCall(oidn_frame, quality, result))
                graph = backend.new_graph()
                backend.begin(graph, pool)
                return result

            try:
                with intercepted_oidn(host):
                    outputs = step(static_frame, static_state)
            except BaseException:
                try:
                    backend.end(graph)
                except RuntimeError:
                    pass
                raise
            backend.end(graph)
            parts.append(graph)
            backend.replay(graph)
        return cls(static_frame, static_state, parts, outputs, backend), clone_tensors(outputs)

    def run(self, frame: Any, state: Any) -> Any:
        copy_into(self.frame, frame)
        copy_into(self.state, state)
        for part in self.parts:
            if isinstance(part, HostCall):
                self.backend.synchronize()
                part.run()
            else:
                self.backend.replay(part)
        return clone_tensors(self.outputs)


FAILED = "failed"  # a structure whose capture raised: it runs eagerly from then on


class GraphCache:
    """Captures by structure, the ``max_graphs`` most recently used kept; how often each structure was seen (a
    structure is captured from its ``warmup + 1``-th call)."""

    def __init__(self, max_graphs: int = MAX_GRAPHS, warmup: int = 1) -> None:
        if max_graphs < 1:
            raise ValueError("max_graphs must be at least 1")
        self.max_graphs, self.warmup = max_graphs, warmup
        self.entries: OrderedDict[Hashable, Any] = OrderedDict()
        self.seen: OrderedDict[Hashable, int] = OrderedDict()

    def get(self, key: Hashable) -> Any:
        entry = self.entries.get(key)
        if entry is not None:
            self.entries.move_to_end(key)
        return entry

    def ready(self, key: Hashable) -> bool:
        """Count a call of an uncaptured structure; True once it has had its warm-up calls."""
        self.seen[key] = self.seen.pop(key, 0) + 1
        while len(self.seen) > 4 * self.max_graphs:
            self.seen.popitem(last=False)
        return self.seen[key] > self.warmup

    def store(self, key: Hashable, entry: Any) -> None:
        self.entries[key] = entry
        self.entries.move_to_end(key)
        while len(self.entries) > self.max_graphs:
            self.entries.popitem(last=False)


class GraphedStep:
    """``step(frame, state)`` through captured graphs where it can (see the module notes)."""

    def __init__(self, step: Callable[[Any, Any], Any], device: torch.device, backend: Any | None = None,
                 max_graphs: int = MAX_GRAPHS) -> None:
        self.step, self.device = step, torch.device(device)
        self.backend = backend if backend is not None else CudaBackend(self.device)
        self.cache = GraphCache(max_graphs)
        self.lock = threading.Lock()
        self.captures = 0  # how many structures were captured (tests and benchmarks read it)

    def _graphable(self, frame: Any, state: Any) -> bool:
        devices = {tensor.device for name, tensor in _tensors((frame, state)) if name not in HOST_FIELDS}
        if devices != {self.device}:
            return False
        cut = getattr(frame, "camera_cut", None)
        return cut is None or not bool(cut.any())

    def __call__(self, frame: Any, state: Any) -> Any:
        if not self._graphable(frame, state):
            return self.step(frame, state)
        key = structure_key((frame, state))
        with self.lock:
            entry = self.cache.get(key)
            if entry == FAILED:
                return self.step(frame, state)
            if entry is None and not self.cache.ready(key):
                with self.backend.side_stream():  # the warm-up
                    return self.step(frame, state)
            if entry is not None:
                return entry.run(frame, state)
            try:
                captured, outputs = CapturedStep.capture(self.step, frame, state, self.backend)
            except RuntimeError as error:  # e.g. a host read of a device value inside the step
                log.warning("a CUDA graph capture of this step failed (%s); this structure runs eagerly", error)
                self.cache.store(key, FAILED)
                return self.step(frame, state)
            self.captures += 1
            self.cache.store(key, captured)
            return outputs


def with_cuda_graphs(method: nn.Module, device: torch.device | str, max_graphs: int = MAX_GRAPHS,
                     backend: Any | None = None) -> nn.Module:
    """The method (in place) with its ``step`` replayed from CUDA graphs on ``device``; unchanged off CUDA, without
    a CUDA runtime (unless a ``backend`` stands in for it) or when it already runs graphs."""
    device = torch.device(device)
    if getattr(method, "_cuda_graphs", None) is not None:
        return method
    if backend is None and (device.type != "cuda" or not torch.cuda.is_available()):
        return method
    graphed = GraphedStep(method.step, device, backend, max_graphs)
    object.__setattr__(method, "step", graphed)
    object.__setattr__(method, "_cuda_graphs", graphed)
    return method
