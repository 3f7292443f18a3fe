"""Export a method's per-frame step for engines: ONNX, the history as explicit inputs and outputs.

An engine calls the exported graph once per frame::

    output, state_out.* = step(color, albedo, normal, depth, motion, jitter, [optional buffers],
                               [spatial_estimate], state.*)

Inputs are the frame bundle's buffers at render resolution, NCHW float32 with N = 1 (optional buffers only when
exported ``with_optional``); ``state.NAME`` is fed back from the previous frame's ``state_out.NAME``, zeros of the
recorded shapes on the first frame and after a cut (a zeroed history is the methods' own "no history"). The
resolution is fixed at export. Methods with a spatial prior (the fused family) are exported without OIDN, a native
library: the engine runs OIDN itself and passes its output as ``spatial_estimate``. OIDN alone, OIDN + TAA and int8
JNDS have nothing the exporter takes and are refused with ``ExportError``. ``check_export`` runs the file
(onnxruntime) beside the method with the history carried and passes within ``TOLERANCE``. TorchScript is not
offered (``UNSUPPORTED_FORMATS`` says why): the shared kernel ops are custom autograd functions that a traced
TorchScript module cannot save, and ONNX goes through ``torch.export``, which traces into them. ``Stages`` names
each stage as it starts and keeps its seconds (the command prints both); the ONNX graph gets a light clean-up
(constant folding, dead and duplicate nodes) instead of onnxscript's full optimizer, whose pattern rewriter took
most of an export's time for little gain in the graph (docs/export.md, "Export time").
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from model.methods.base import FrameBatch, Method

FORMATS = ("onnx",)
UNSUPPORTED_FORMATS = {
    "torchscript": "TorchScript export is not supported: the methods' kernel ops are custom autograd functions, "
                   "which a torch.jit.trace'd module cannot save ('Could not export Python function call') and "
                   "torch.jit.script cannot compile; use onnx (torch.export traces into them)"}
REQUIRED_INPUTS = ("color", "albedo", "normal", "depth", "motion", "jitter")
OPTIONAL_INPUTS = ("diffuse", "specular", "specular_albedo", "roughness")
SPATIAL_INPUT = "spatial_estimate"
TOLERANCE = {"atol": 1e-4, "rtol": 1e-4}
CHECK_JITTERS = ((0.3, -0.2), (-0.35, 0.15), (0.1, 0.4), (-0.15, -0.4))  # off the quarters, where reads tie


class ExportError(ValueError):
    """The method cannot be exported (OIDN inside, int8 eager modules, an exporter failure), or a bad request."""


class Stages:
    """The stages of an export and its check: ``say`` gets a line as each starts (the command prints them on
    stderr, so a long stage does not look like a hang); ``seconds`` keeps each one's wall time."""

    def __init__(self, say: Callable[[str], None] | None = None) -> None:
        self.say = say or (lambda line: None)
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str, doing: str) -> Iterator[None]:
        self.say(f"{name}: {doing} ...")
        started = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - started

    def summary(self) -> str:
        parts = ", ".join(f"{name} {seconds:.1f}" for name, seconds in self.seconds.items())
        return f"{sum(self.seconds.values()):.1f} s in all ({parts})"


class _Step(nn.Module):
    """``method.step`` with the frame's buffers and the state as flat tensors (what exporters take)."""

    def __init__(self, method: Method, inputs: tuple[str, ...], state_names: tuple[str, ...]) -> None:
        super().__init__()
        self.method = method
        self.inputs = inputs
        self.state_names = state_names

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        named = dict(zip(self.inputs, tensors))
        frame = FrameBatch(camera_cut=torch.zeros(1, dtype=torch.bool), **named)
        state = dict(zip(self.state_names, tensors[len(self.inputs):]))
        output, new_state = self.method.step(frame, state)
        # clone: a state entry that is an input passed through (depth, normal, jitter) must be a graph output too.
        return (output, *[new_state[name].clone() for name in self.state_names])


def check_exportable(method: Method) -> None:
    """ExportError naming why ``method`` has no exportable per-frame network."""
    label = method.label
    if not method.learned:
        raise ExportError(f"{label} has no network to export: "
                          + ("it is OIDN's native library (run OIDN in the engine)" if method.name.startswith("oidn")
                             else "it is a filter without weights; only trained models are exported"))
    if method.preset.endswith("-int8"):
        raise ExportError(f"{label} runs eager-mode int8 quantized modules (torch.ao), which neither ONNX nor "
                          f"TorchScript export takes; export the float32 checkpoint it was fine-tuned from")


def exported_form(method: Method) -> Method:
    """The method as the export runs it. A fused model with a sample mean (``sample_mean_frames``) runs OIDN on a
    running mean of the frames held in its state, inside its step; an engine passes OIDN's output in from outside,
    so the export takes OIDN of the single frame, as every fused model before the sample mean did (a copy with the
    setting at 0; the interface says so)."""
    if not getattr(method, "sample_mean_frames", 0):
        return method
    single = copy.deepcopy(method)
    single.set_sample_mean_frames(0)
    return single


def example_inputs(method: Method, height: int, width: int, with_optional: bool = False,
                   seed: int = 0) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """(frame inputs by name, the state after one step on them): shapes for the export and a first frame."""
    inputs = _example_frame(method, height, width, with_optional, seed)
    with torch.no_grad():
        _, state = method.step(_frame(inputs), None)
    # Copies: a state entry may be an input tensor itself (depth, normal, jitter), and an exporter given the same
    # tensor twice merges the two inputs into one.
    return inputs, {name: tensor.clone() for name, tensor in state.items()}


def _example_frame(method: Method, height: int, width: int, with_optional: bool, seed: int) -> dict[str, torch.Tensor]:
    from model.methods.registry import example_batch

    frame = example_batch(height, width, seed=seed)
    inputs = {name: getattr(frame, name) for name in REQUIRED_INPUTS}
    if with_optional:
        inputs.update({name: getattr(frame, name) for name in OPTIONAL_INPUTS})
    if getattr(method, "spatial_prior", None):
        inputs[SPATIAL_INPUT] = frame.color * 0.5  # any plausible radiance: only shapes matter for the trace
    return inputs


def _frame(inputs: dict[str, torch.Tensor]) -> FrameBatch:
    return FrameBatch(camera_cut=torch.zeros(1, dtype=torch.bool), **inputs)


def interface(method: Method, inputs: dict[str, torch.Tensor], state: dict[str, torch.Tensor],
              sample_mean_frames: int = 0) -> dict[str, Any]:
    """What an engine needs to call the exported step: names and shapes of inputs, state and outputs
    (``sample_mean_frames``: the model's sample mean, which the export leaves out; see ``exported_form``)."""
    sample_mean = None
    if sample_mean_frames:
        sample_mean = (f"not exported: in PyTorch this model's OIDN reads a running mean of up to {sample_mean_frames} "
                       f"frames kept in its state; the exported step takes OIDN of the single frame")
    return {"format": "denoiser-export/1", "method": method.name, "preset": method.preset, "scale": method.scale,
            "inputs": {name: list(tensor.shape) for name, tensor in inputs.items()},
            "state": {name: list(tensor.shape) for name, tensor in sorted(state.items())},
            "outputs": {"output": [1, 3, inputs["color"].shape[2] * method.scale,
                                   inputs["color"].shape[3] * method.scale],
                        **{f"state_out.{name}": list(tensor.shape) for name, tensor in sorted(state.items())}},
            "first_frame": "state inputs all zeros (also after a camera cut)",
            "spatial_estimate": ("OIDN's output at render resolution (linear radiance, quality "
                                 f"'{method.preset}', albedo + normal, clean aux)") if SPATIAL_INPUT in inputs else None,
            "sample_mean": sample_mean,
            "tolerance": TOLERANCE}


def export_step(method: Method, path: str | os.PathLike, fmt: str = "onnx", height: int = 128, width: int = 128,
                with_optional: bool = False, stages: Stages | None = None) -> dict[str, Any]:
    """Write ``method``'s per-frame step to ``path``; returns its interface (also stored in the file's metadata,
    ONNX ``metadata_props['denoiser']``). ``stages`` hears of and times each stage."""
    if fmt in UNSUPPORTED_FORMATS:
        raise ExportError(UNSUPPORTED_FORMATS[fmt])
    if fmt not in FORMATS:
        raise ExportError(f"format {fmt!r} is not one of {', '.join(FORMATS)}")
    check_exportable(method)
    stages = stages or Stages()
    sample_mean_frames = getattr(method, "sample_mean_frames", 0)
    with stages.stage("prepare", f"the step of {method.label} on an example {width}x{height} frame"):
        method = exported_form(method).cpu().for_inference().eval()
        for parameter in method.parameters():
            parameter.requires_grad_(False)
        inputs, state = example_inputs(method, height, width, with_optional)
    state_names = tuple(sorted(state))
    module = _Step(method, tuple(inputs), state_names).eval()
    arguments = (*inputs.values(), *[state[name] for name in state_names])
    info = interface(method, inputs, state, sample_mean_frames)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # tracer and exporter chatter about constants and deprecations
            _export_onnx(module, arguments, inputs, state_names, path, info, stages)
    except ExportError:
        raise
    except Exception as error:  # the exporters raise many types; the first line says what failed
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise ExportError(f"{method.label} could not be exported to {fmt}: {first}") from None
    return info


def _export_onnx(module: nn.Module, arguments: tuple, inputs: dict, state_names: tuple, path: Path,
                 info: dict, stages: Stages) -> None:
    import io

    with stages.stage("torch.export", "tracing the step into an ExportedProgram"):
        try:
            program = torch.export.export(module, arguments, strict=False)
        except Exception:  # torch.onnx.export tries its other capture strategies on the module itself
            program = module
    with stages.stage("onnx", "translating the graph to ONNX"), contextlib.redirect_stdout(io.StringIO()):
        import onnx  # in the stage: importing the ONNX packages takes seconds

        # optimize=False: onnxscript's full optimizer spent most of its time in pattern rewrites (see _tidy_graph).
        onnx_program = torch.onnx.export(program, arguments, dynamo=True, external_data=False, optimize=False,
                                         input_names=[*inputs, *[f"state.{name}" for name in state_names]],
                                         output_names=["output", *[f"state_out.{name}" for name in state_names]])
    with stages.stage("optimize", "folding constants, removing dead and duplicate nodes"):
        _tidy_graph(onnx_program)
    with stages.stage("write", str(path)):
        proto = onnx_program.model_proto
        entry = proto.metadata_props.add()
        entry.key, entry.value = "denoiser", json.dumps(info)
        onnx.save(proto, str(path))


def _tidy_graph(onnx_program) -> None:
    """The graph-shrinking part of onnxscript's optimizer (constant folding, dead nodes, common subexpressions,
    duplicate initializers) without its pattern rewriter, which took most of the optimizer's time and left
    onnxruntime's speed unchanged (it rewrites what runtimes fuse themselves; docs/export.md, "Export time")."""
    try:
        import onnx_ir.passes.common as passes
        from onnxscript.optimizer import fold_constants
    except ImportError:  # an onnxscript without these passes: its full optimizer, slower but the same graph
        onnx_program.optimize()
        return
    model = onnx_program.model
    passes.InlinePass()(model)
    for _ in range(2):  # folding exposes more to fold once dead nodes are gone, as the full optimizer iterates
        fold_constants(model)
        passes.RemoveUnusedNodesPass()(model)
    for tidy in (passes.IdentityEliminationPass(), passes.RemoveUnusedNodesPass(), passes.RemoveUnusedFunctionsPass(),
                 passes.RemoveUnusedOpsetsPass(),
                 passes.LiftConstantsToInitializersPass(lift_all_constants=True, size_limit=0),
                 passes.DeduplicateInitializersPass(), passes.CommonSubexpressionEliminationPass(),
                 passes.RemoveUnusedNodesPass(), passes.OutputFixPass(), passes.NameFixPass()):
        tidy(model)


def run_exported(path: str | os.PathLike, frames: list[dict[str, torch.Tensor]],
                 state_shapes: dict[str, list[int]]) -> list[torch.Tensor]:
    """Outputs of the exported step (onnxruntime) over ``frames`` (inputs by name), zeros as the first state, the
    history fed back from frame to frame."""
    import onnxruntime

    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = sorted(state_shapes)
    state = {name: torch.zeros(state_shapes[name]) for name in names}
    outputs = []
    for frame in frames:
        feed = {name: tensor.numpy() for name, tensor in frame.items()}
        feed.update({f"state.{name}": state[name].numpy() for name in names})
        result = session.run(None, feed)
        outputs.append(torch.from_numpy(result[0]))
        state = {name: torch.from_numpy(value) for name, value in zip(names, result[1:])}
    return outputs


def check_export(method: Method, path: str | os.PathLike, info: dict[str, Any], frames: int = 4,
                 seed: int = 1, stages: Stages | None = None) -> float:
    """The largest |exported - PyTorch| over a sequence of ``frames`` random frames (history carried; PyTorch's first
    step without a state, the export's with zeros), in units of the tolerance: <= 1 passes."""
    stages = stages or Stages()
    height, width = info["inputs"]["color"][2:]
    expected, state, sequence = [], None, []
    with stages.stage("check pytorch", f"running the method over {frames} frames"), torch.no_grad():
        method = exported_form(method).cpu().for_inference().eval()
        for index in range(frames):
            inputs = _example_frame(method, height, width, "diffuse" in info["inputs"], seed + index)
            # jittered as an engine renders them: at zero jitter every path that reads the jitter would go unchecked
            inputs["jitter"] = torch.tensor([CHECK_JITTERS[index % len(CHECK_JITTERS)]])
            sequence.append(inputs)
        for inputs in sequence:
            output, state = method.step(_frame(inputs), state)
            expected.append(output)
    with stages.stage("check onnxruntime", f"running the file over {frames} frames"):
        actual = run_exported(path, sequence, info["state"])
    worst = 0.0
    for got, want in zip(actual, expected):
        allowed = TOLERANCE["atol"] + TOLERANCE["rtol"] * want.abs()
        worst = max(worst, float(((got - want).abs() / allowed).max()))
    return worst
