"""Time JNDS float32 against its int8 forms in one run, and say how much of the step int8 can reach at all.

    .venv/bin/python scripts/bench_int8.py                          # preset s, 128x128 -> 256x256, 1 thread
    .venv/bin/python scripts/bench_int8.py --shipped --sizes 128 256 # the shipped jnds-s-x2 / jnds-s-int8-x2 pair
    .venv/bin/python scripts/bench_int8.py --checkpoint runs/jnds-s/best.pt --pt2e   # + PT2E int8 (torchao)

Without ``--shipped`` both forms are one network: float32 weights (random, or ``--checkpoint``) loaded into the
QAT model (``JNDS.load_float_weights``), its activation ranges calibrated on a few frames, then converted to int8
(``for_inference``). ``--shipped`` times the pretrained float32 model against the shipped int8 one (their own
weights). ``--pt2e`` adds torch.compile forms of the float32 model's network: float32, and int8 quantized with
torchao's PT2E ``X86InductorQuantizer`` (torchao must be installed; it is not a project dependency; a C++
compiler runs at start-up, once per frame size). Timed is one whole ``step`` with history, on synthetic frames
(``example_batch``: timing does not depend on the content), after warm-up; forms run interleaved, one frame each
in turn, medians reported. Also printed: the share of the float32 step spent in the network (the part int8
replaces; the filters, warps and heads stay float32), the speed-up bound it sets, and each form's display PSNR
against the float32 output. Findings: docs/results/int8.md.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.deployment.pretrained import load_pretrained  # noqa: E402
from model.evaluation.metrics import psnr  # noqa: E402
from model.methods.base import FrameBatch, State  # noqa: E402
from model.methods.jnds import INT8_SUFFIX, JNDS, PRESETS  # noqa: E402
from model.methods.registry import example_batch  # noqa: E402
from model.ops.tonemap import display_encode  # noqa: E402
from model.training.checkpoint import load_checkpoint  # noqa: E402

CALIBRATION_FRAMES = 4
SEQUENCE_LENGTH = 8  # distinct synthetic frames, cycled
SHIPPED = ("jnds-s-x2", "jnds-s-int8-x2")


class TimedForm:
    """One inference form of the method, stepping through the frames with its own history; it also times the
    network's two calls (``forward`` and ``predict_upsample``) inside each step."""

    def __init__(self, name: str, method: JNDS) -> None:
        self.name = name
        self.method = method
        self.state: State | None = None
        self.times: list[float] = []
        self.network_times: list[float] = []
        self._network_time = 0.0
        network = method.network
        network.forward = self._timed(network.forward)
        network.predict_upsample = self._timed(network.predict_upsample)

    def _timed(self, call: Callable) -> Callable:
        def timed(*args):
            started = time.perf_counter()
            result = call(*args)
            self._network_time += time.perf_counter() - started
            return result
        return timed

    def step(self, frame: FrameBatch, record: bool) -> torch.Tensor:
        self._network_time = 0.0
        started = time.perf_counter()
        output, self.state = self.method.step(frame, self.state)
        if record:
            self.times.append(time.perf_counter() - started)
            self.network_times.append(self._network_time)
        return output

    @property
    def median_ms(self) -> float:
        return statistics.median(self.times) * 1e3

    @property
    def network_ms(self) -> float:
        return statistics.median(self.network_times) * 1e3


def float_and_int8(preset: str, scale: int, frames: list[FrameBatch], checkpoint: Path | None,
                   shipped: bool) -> tuple[JNDS, JNDS]:
    """(float32, int8) JNDS in inference form: the shipped pair, or one set of weights and its calibrated int8."""
    if shipped:
        return load_pretrained(SHIPPED[0]).for_inference(), load_pretrained(SHIPPED[1]).for_inference()
    torch.manual_seed(0)
    float_method = JNDS(preset, scale)
    if checkpoint is not None:
        content = load_checkpoint(checkpoint)
        if content["method"] != float_method.config():
            raise SystemExit(f"{checkpoint} holds {content['method']}, not {float_method.config()}")
        float_method.load_state_dict(content["model"])
    float_method.eval()
    qat = JNDS(preset + INT8_SUFFIX, scale)
    qat.load_float_weights(float_method.state_dict())
    with torch.no_grad():  # training mode, no gradients: the observers record activation ranges
        state = None
        for frame in frames[:CALIBRATION_FRAMES]:
            _, state = qat.step(frame, state)
    return float_method, qat.for_inference()


def pt2e_forms(float_method: JNDS, frames: list[FrameBatch]) -> list[tuple[str, JNDS]]:
    """torch.compile forms of ``float_method``'s network: float32, and PT2E int8 calibrated on ``frames``."""
    try:
        from torchao.quantization.pt2e.quantize_pt2e import convert_pt2e, prepare_pt2e
        from torchao.quantization.pt2e.quantizer import x86_inductor_quantizer as x86
    except ImportError:
        raise SystemExit("--pt2e needs torchao (pip install torchao), which the project does not depend on") from None
    import torch._inductor.config as inductor_config

    inductor_config.freezing = True  # constant weights: prepacked int8 convolutions
    calls: dict[str, list[tuple[torch.Tensor, ...]]] = {"forward": [], "predict_upsample": []}
    recorder = copy.deepcopy(float_method)
    for name in calls:
        original = getattr(recorder.network, name)
        setattr(recorder.network, name, lambda *args, _o=original, _n=name: (
            calls[_n].append(tuple(a.clone() for a in args)), _o(*args))[1])
    with torch.no_grad():
        state = None
        for frame in frames[:CALIBRATION_FRAMES]:
            _, state = recorder.step(frame, state)

    def quantized(module: torch.nn.Module, samples: list[tuple[torch.Tensor, ...]]) -> torch.nn.Module:
        quantizer = x86.X86InductorQuantizer().set_global(x86.get_default_x86_inductor_quantization_config())
        prepared = prepare_pt2e(torch.export.export(module, samples[0]).module(), quantizer)
        for sample in samples:
            prepared(*sample)
        return convert_pt2e(prepared)

    forms = []
    for label, quantize in (("fp32 compiled", False), ("int8 PT2E compiled", True)):
        method = copy.deepcopy(float_method)
        network = copy.deepcopy(method.network)
        forward, upsample = _Forward(network).eval(), _Upsample(network).eval()
        if quantize:
            forward, upsample = quantized(forward, calls["forward"]), quantized(upsample, calls["predict_upsample"])
        compiled_forward, compiled_upsample = torch.compile(forward), torch.compile(upsample)
        method.network.forward = lambda x, _f=compiled_forward: _unflatten(_f(x))
        method.network.predict_upsample = lambda guide, features, _u=compiled_upsample: _u(guide, features)
        forms.append((label, method))
    return forms


class _Forward(torch.nn.Module):
    """The network's forward with a flat tuple output, as torch.export takes it."""

    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        levels, native, features = self.network(inputs)
        return (*levels, native, features)


class _Upsample(torch.nn.Module):
    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, guide: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return self.network.predict_upsample(guide, features)


def _unflatten(outputs: tuple[torch.Tensor, ...]) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    return list(outputs[:-2]), outputs[-2], outputs[-1]


def run_size(size: int, args: argparse.Namespace) -> dict:
    frames = [example_batch(size, size, seed=seed) for seed in range(SEQUENCE_LENGTH)]
    float_method, int8 = float_and_int8(args.preset, args.scale, frames, args.checkpoint, args.shipped)
    named = [("fp32", float_method), ("int8 eager", int8)]
    if args.pt2e:
        named += pt2e_forms(float_method, frames)
    forms = [TimedForm(name, method) for name, method in named]
    agreement: dict[str, list[float]] = {form.name: [] for form in forms}
    with torch.no_grad():
        for index in range(args.warmup + args.frames):
            frame = frames[index % len(frames)]
            outputs = [form.step(frame, record=index >= args.warmup) for form in forms]
            reference = display_encode(outputs[0])
            for form, output in zip(forms, outputs):
                agreement[form.name].append(float(psnr(display_encode(output), reference).mean()))
    fp32 = forms[0]
    share = fp32.network_ms / fp32.median_ms
    return {"render": size, "output": size * args.scale, "threads": args.threads,
            "forms": {form.name: {"ms": form.median_ms, "network_ms": form.network_ms,
                                  "speedup": fp32.median_ms / form.median_ms,
                                  "display_psnr_vs_fp32": statistics.mean(agreement[form.name])}
                      for form in forms},
            "network_share": share, "bound_if_network_free": 1.0 / (1.0 - share)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="s", choices=sorted(PRESETS))
    parser.add_argument("--sizes", type=int, nargs="+", default=[128], help="render resolutions (square), pixels")
    parser.add_argument("--scale", type=int, default=2, choices=(1, 2))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--frames", type=int, default=30, help="timed frames per form")
    parser.add_argument("--checkpoint", type=Path, default=None, help="float32 JNDS checkpoint to time")
    parser.add_argument("--shipped", action="store_true", help=f"time the pretrained {' and '.join(SHIPPED)}")
    parser.add_argument("--pt2e", action="store_true", help="add torch.compile fp32 and PT2E int8 forms (torchao)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args(argv)
    if args.shipped and (args.checkpoint is not None or args.preset != "s" or args.scale != 2):
        parser.error("--shipped times the pretrained pair (preset s, scale 2); drop --checkpoint/--preset/--scale")

    torch.set_num_threads(args.threads)
    print(f"JNDS:{args.preset} x{args.scale}{' (shipped weights)' if args.shipped else ''}, {args.threads} "
          f"thread(s), median of {args.frames} frames after {args.warmup} warm-up, forms interleaved; quantized "
          f"engine {torch.backends.quantized.engine}, CPU capability {torch.backends.cpu.get_cpu_capability()}")
    results = []
    for size in args.sizes:
        result = run_size(size, args)
        results.append(result)
        out = result["output"]
        print(f"{size}x{size} -> {out}x{out}: the network is {100 * result['network_share']:.0f}% of the fp32 "
              f"step, so int8 of the network alone is at most {result['bound_if_network_free']:.2f}x")
        for name, form in result["forms"].items():
            print(f"  {name:<20} {form['ms']:8.1f} ms/frame (network {form['network_ms']:6.1f})  "
                  f"{form['speedup']:5.2f}x fp32   display PSNR vs fp32 {form['display_psnr_vs_fp32']:6.1f} dB")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "results": results},
                                        indent=2))


if __name__ == "__main__":
    main()
