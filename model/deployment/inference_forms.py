"""Fast inference forms: how a method's networks run on this CPU, chosen per method and resolution by measurement.

A method's ``step`` is its networks (the children that hold parameters) plus float32 work around them: warps,
filtering with predicted kernels, history blends. A form changes how the networks run, so histories, kernels and
outputs stay float32 whatever the form: ``eager`` (fp32, as ``for_inference()`` leaves them), ``channels_last``,
``bf16`` (CPU autocast, outputs cast back), ``channels_last+bf16``, ``compile`` / ``compile+bf16``
(``torch.compile`` of the networks, chosen only where the table allows it). ``compile-step`` / ``compile-step+bf16``
also compile the float32 work around the networks, the whole step, into few fused loops
(``model.deployment.compiled_step``, eager again if compiling fails); the networks run eagerly in fp32 or bf16. The
first frames at a new resolution compile there: the table chooses them where a method's step is mostly that work
(the fused family). The form is read from a table that ``scripts/bench_inference_forms.py`` measures per
method key (``wskpn:s:x1``: registry name, preset and scale) and render resolution: the fastest form whose output
stays within ``MIN_PSNR_DB`` of eager fp32 on every frame. A frame takes the row of the nearest measured resolution
in pixel count. Forms apply on the CPU (on CUDA the step runs from ``model.deployment.cuda_graph``); an entry
that needs bf16 on a CPU without it falls back to the fastest measured form without bf16. More: docs/methods.md,
"Inference forms" and "Fast forms of the fused step".
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from model.deployment.compiled_step import CompiledStep
from model.ops.graph_breaks import outside_compiled_graph

__all__ = ["FORMS", "InferenceForm", "FormTable", "MIN_PSNR_DB", "SHIPPED_TABLE", "form_psnr", "load_form_table",
           "method_key", "networks_of", "run_networks_as", "with_inference_forms", "bf16_available"]

MIN_PSNR_DB = 50.0  # a form's output against the eager fp32 output, display-encoded, on every frame of a stream
SHIPPED_TABLE = Path(__file__).with_name("inference_forms.json")


@dataclass(frozen=True)
class InferenceForm:
    name: str
    channels_last: bool = False
    bf16: bool = False
    compiled: bool = False
    compiled_step: bool = False  # the method's whole step compiled around its networks (model.deployment.compiled_step)


FORMS = {form.name: form for form in (
    InferenceForm("eager"),
    InferenceForm("channels_last", channels_last=True),
    InferenceForm("bf16", bf16=True),
    InferenceForm("channels_last+bf16", channels_last=True, bf16=True),
    InferenceForm("compile", compiled=True),
    InferenceForm("compile+bf16", compiled=True, bf16=True),
    InferenceForm("compile-step", compiled_step=True),
    InferenceForm("compile-step+bf16", bf16=True, compiled_step=True),
)}


def form_psnr(output: torch.Tensor, eager: torch.Tensor) -> float:
    """How far a form's output is from the eager fp32 one: PSNR in dB of the two tone-mapped with x / (1 + x)
    (the range where a difference shows; 200 for identical images), the measure ``MIN_PSNR_DB`` applies to."""
    output, eager = torch.as_tensor(output).clamp_min(0), torch.as_tensor(eager).clamp_min(0)
    mse = float(((output / (1 + output) - eager / (1 + eager)) ** 2).mean())
    return 200.0 if mse == 0 else min(200.0, -10 * math.log10(mse))


def bf16_available() -> bool:
    """Whether this CPU runs bfloat16 convolutions natively (oneDNN with AVX-512 BF16 or AMX)."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def method_key(method: nn.Module) -> str:
    """``name:preset:xS``: forms are measured per architecture, not per weights."""
    return f"{method.name}:{method.preset}:x{method.scale}"


def networks_of(method: nn.Module) -> list[nn.Module]:
    """The method's networks: its direct children that hold parameters."""
    return [child for child in method.children() if any(True for _ in child.parameters())]


class FormTable:
    """The measured table (see the module notes): ``form_for(key, width, height)``."""

    def __init__(self, data: dict[str, Any], allow_compile: bool | None = None) -> None:
        self.data = data
        self.allow_compile = bool(data.get("allow_compile", False)) if allow_compile is None else allow_compile

    @classmethod
    def read(cls, path: str | Path) -> FormTable:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as error:
            raise ValueError(f"cannot read the inference form table {path}: {error}") from error
        if not isinstance(data, dict) or not isinstance(data.get("methods"), dict):
            raise ValueError(f"{path} is not an inference form table (no 'methods' object)")
        return cls(data)

    def keys(self) -> list[str]:
        return sorted(self.data["methods"])

    def form_for(self, key: str, width: int, height: int, bf16: bool | None = None) -> InferenceForm:
        """The form of the measured resolution nearest to ``width`` x ``height`` in pixel count (eager for a key
        the table lacks)."""
        rows = self.data["methods"].get(key)
        if not rows:
            return FORMS["eager"]
        pixels = width * height

        def distance(size: str) -> float:
            w, _, h = size.partition("x")
            return abs(math.log(int(w) * int(h) / pixels))

        row = rows[min(rows, key=distance)]
        bf16 = bf16_available() if bf16 is None else bf16
        usable = [name for name, ms in sorted(row.get("ms", {}).items(), key=lambda item: item[1])
                  if name in FORMS and row.get("psnr_db", {}).get(name, 0.0) >= MIN_PSNR_DB
                  and (bf16 or not FORMS[name].bf16) and (self.allow_compile or not FORMS[name].compiled)]
        chosen = row.get("chosen")
        if chosen in usable:
            return FORMS[chosen]
        return FORMS[usable[0]] if usable else FORMS["eager"]


def load_form_table(spec: FormTable | str | Path | None = "measured") -> FormTable | None:
    """``measured``: the table shipped with the package; ``off`` (or None): no forms, every method eager;
    else the path of a table written by ``scripts/bench_inference_forms.py`` (a FormTable is returned as is)."""
    if isinstance(spec, FormTable):
        return spec
    if spec is None or str(spec) == "off":
        return None
    return FormTable.read(SHIPPED_TABLE if str(spec) == "measured" else spec)


def _to_float32(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        if not value.is_floating_point() or value.dtype == torch.float32:
            return value
        # contiguous as well: a channels_last network's outputs are strided slices, which every later per-channel
        # read pays for (more than the conversion costs)
        return value.to(torch.float32, memory_format=torch.contiguous_format)
    if isinstance(value, tuple):
        return tuple(_to_float32(item) for item in value)
    if isinstance(value, list):
        return [_to_float32(item) for item in value]
    if isinstance(value, dict):
        return {name: _to_float32(item) for name, item in value.items()}
    return value


def _channels_last(value: Any) -> Any:
    if isinstance(value, torch.Tensor) and value.dim() == 4:
        return value.contiguous(memory_format=torch.channels_last)
    return value


class _NetworkForms:
    """A network's forward, run in whichever form the calling thread selected (``run_networks_as``)."""

    def __init__(self, forward: Callable[..., Any], selected: threading.local) -> None:
        self.forward = forward
        self.selected = selected
        self.compiled: Callable[..., Any] | None = None

    @outside_compiled_graph  # inside a compiled step the network runs in its own form
    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        form = getattr(self.selected, "form", None) or FORMS["eager"]
        if form.name == "eager":
            return self.forward(*args, **kwargs)
        if form.channels_last:
            args = tuple(_channels_last(arg) for arg in args)
        forward = self.forward
        if form.compiled:
            if self.compiled is None:
                self.compiled = torch.compile(self.forward, dynamic=False)
            forward = self.compiled
        context = torch.autocast("cpu", dtype=torch.bfloat16) if form.bf16 else nullcontext()
        with context:
            output = forward(*args, **kwargs)
        return _to_float32(output) if form.bf16 else output


def _install(method: nn.Module) -> threading.local:
    """Route the method's networks through ``_NetworkForms`` and its step through ``_route_step`` (once); the
    thread-local form selector."""
    selected = getattr(method, "_form_selector", None)
    if selected is None:
        selected = threading.local()
        for network in networks_of(method):
            network.forward = _NetworkForms(network.forward, selected)
        object.__setattr__(method, "_form_selector", selected)

        def network_input_dtype() -> torch.dtype:
            form = getattr(selected, "form", None)
            # compiled networks trace their own casts; an eager bf16 form casts the input first thing
            bf16 = form is not None and form.bf16 and not form.compiled and not form.compiled_step
            return torch.bfloat16 if bf16 else torch.float32

        object.__setattr__(method, "network_input_dtype", network_input_dtype)
        compiled = CompiledStep(method.step)
        object.__setattr__(method, "_compiled_step", compiled)  # benchmarks and tests read its failure
        object.__setattr__(method, "step", _route_step(method.step, compiled, selected))
    return selected


def _route_step(step: Callable[[Any, Any], Any], compiled: CompiledStep,
                selected: threading.local) -> Callable[[Any, Any], Any]:
    """The step, compiled whole while the calling thread's form says so, else as it was."""

    def routed_step(frame: Any, state: Any) -> Any:
        form = getattr(selected, "form", None)
        return compiled(frame, state) if form is not None and form.compiled_step else step(frame, state)

    return routed_step


class run_networks_as:  # noqa: N801 (a context manager, used like a function)
    """``with run_networks_as(method, form): method.step(...)``: the method's networks run in ``form`` on this
    thread (the benchmark and the tests pick forms by hand; ``with_inference_forms`` picks them by the table)."""

    def __init__(self, method: nn.Module, form: InferenceForm | str) -> None:
        self.selected = _install(method)
        self.form = FORMS[form] if isinstance(form, str) else form

    def __enter__(self) -> None:
        self.previous = getattr(self.selected, "form", None)
        self.selected.form = self.form

    def __exit__(self, *exc: object) -> None:
        self.selected.form = self.previous


def with_inference_forms(method: nn.Module, table: FormTable | None,
                         device: torch.device | str = "cpu") -> nn.Module:
    """The method (in place) with its ``step`` running its networks in the table's form for each frame's
    resolution; unchanged without a table, for a method the table has no row for, or one that already runs a
    table's forms. On CUDA the form is the step replayed from CUDA graphs (``model.deployment.cuda_graph``)."""
    if table is not None and torch.device(device).type == "cuda":
        from model.deployment.cuda_graph import with_cuda_graphs

        return with_cuda_graphs(method, device)
    if table is None or torch.device(device).type != "cpu" or method_key(method) not in table.keys() \
            or not networks_of(method) or getattr(method, "_form_table", None) is not None:
        return method
    selected = _install(method)
    key, step = method_key(method), method.step
    # Sessions of different resolutions share one loaded method across threads: the form is per thread, per call.

    def step_in_form(frame: Any, state: Any) -> Any:
        height, width = frame.color.shape[-2:]
        previous = getattr(selected, "form", None)
        selected.form = table.form_for(key, int(width), int(height))
        try:
            return step(frame, state)
        finally:
            selected.form = previous

    object.__setattr__(method, "step", step_in_form)
    object.__setattr__(method, "_form_table", table)  # once: a second call leaves the method as it is
    return method
