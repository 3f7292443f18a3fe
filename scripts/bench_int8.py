"""Time JNDS float32 against its int8 form: milliseconds per frame and the int8 speed-up, on this CPU.

    .venv/bin/python scripts/bench_int8.py                       # preset s, 128x128 -> 256x256, 2 threads
    .venv/bin/python scripts/bench_int8.py --preset m --frames 40 --threads 1
    .venv/bin/python scripts/bench_int8.py --checkpoint runs/jnds-s/best.pt   # trained float32 weights

Both forms are the same network: the float32 model's weights are loaded into the QAT model
(``JNDS.load_float_weights``), its activation ranges calibrated on a few frames, and then it is converted to
int8 (``for_inference``). Timed is one whole ``step`` (network, filters, warps, upsampling) with history, on
synthetic frames (``example_batch``: timing does not depend on the content), in inference mode, after warm-up
frames; the median over the timed frames is reported. The forms run interleaved, one frame each in turn, so
load from other processes on a shared machine hits every form alike. Also printed: how far the int8 output is
from the fake-quantized (QAT) model's, which it should reproduce. Quality against float32 needs trained
weights and references: that is the evaluation command's job.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.training.checkpoint import load_checkpoint  # noqa: E402
from model.methods.base import FrameBatch, Method, State  # noqa: E402
from model.methods.jnds import INT8_SUFFIX, JNDS, PRESETS  # noqa: E402
from model.methods.registry import example_batch  # noqa: E402

CALIBRATION_FRAMES = 4
SEQUENCE_LENGTH = 8  # distinct synthetic frames, cycled


class TimedForm:
    """One inference form of the method, stepping through the frames with its own history."""

    def __init__(self, name: str, method: Method, channels_last_inputs: bool = False) -> None:
        self.name = name
        self.method = method
        self.channels_last_inputs = channels_last_inputs
        self.state: State | None = None
        self.times: list[float] = []

    def step(self, frame: FrameBatch, record: bool) -> torch.Tensor:
        started = time.perf_counter()
        output, self.state = self.method.step(frame, self.state)
        if record:
            self.times.append(time.perf_counter() - started)
        return output

    @property
    def median_ms(self) -> float:
        return statistics.median(self.times) * 1e3


def build_forms(preset: str, scale: int, frames: list[FrameBatch],
                checkpoint: Path | None) -> tuple[JNDS, JNDS, JNDS, JNDS]:
    """(float32 eager, float32 channels_last, int8, and the QAT model calibrated on ``frames`` that int8 came from)."""
    torch.manual_seed(0)
    float_method = JNDS(preset, scale)
    if checkpoint is not None:
        content = load_checkpoint(checkpoint)
        if content["method"] != float_method.config():
            raise SystemExit(f"{checkpoint} holds {content['method']}, not {float_method.config()}")
        float_method.load_state_dict(content["model"])
    float_method.eval()
    channels_last = copy.deepcopy(float_method).to(memory_format=torch.channels_last)
    qat = JNDS(preset + INT8_SUFFIX, scale)
    qat.load_float_weights(float_method.state_dict())
    with torch.no_grad():  # training mode, no gradients: the observers record activation ranges
        state = None
        for frame in frames[:CALIBRATION_FRAMES]:
            _, state = qat.step(frame, state)
    qat.eval()
    int8 = copy.deepcopy(qat).for_inference()
    return float_method, channels_last, int8, qat


def qat_agreement(qat: JNDS, int8: JNDS, frames: list[FrameBatch]) -> tuple[float, float]:
    """(max |int8 - QAT|, mean |QAT|) over two steps."""
    worst, scale = 0.0, 0.0
    qat_state = int8_state = None
    with torch.inference_mode():
        for frame in frames[:2]:
            expected, qat_state = qat.step(frame, qat_state)
            got, int8_state = int8.step(frame, int8_state)
            worst = max(worst, float((got - expected).abs().max()))
            scale = max(scale, float(expected.abs().mean()))
    return worst, scale


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="s", choices=sorted(PRESETS))
    parser.add_argument("--size", type=int, default=128, help="render resolution (square), pixels")
    parser.add_argument("--scale", type=int, default=2, choices=(1, 2))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--frames", type=int, default=30, help="timed frames per form")
    parser.add_argument("--checkpoint", type=Path, default=None, help="float32 JNDS checkpoint to time")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    frames = [example_batch(args.size, args.size, seed=seed) for seed in range(SEQUENCE_LENGTH)]
    float_method, channels_last, int8, qat = build_forms(args.preset, args.scale, frames, args.checkpoint)
    forms = [TimedForm("fp32", float_method), TimedForm("fp32 channels_last", channels_last),
             TimedForm("int8", int8)]
    with torch.inference_mode():
        for index in range(args.warmup + args.frames):
            frame = frames[index % len(frames)]
            for form in forms:
                form.step(frame, record=index >= args.warmup)

    out = args.size * args.scale
    print(f"JNDS:{args.preset}, {args.size}x{args.size} -> {out}x{out}, {args.threads} threads, "
          f"median of {args.frames} frames after {args.warmup} warm-up, forms interleaved; "
          f"quantized engine {torch.backends.quantized.engine}, CPU capability "
          f"{torch.backends.cpu.get_cpu_capability()}")
    for form in forms:
        print(f"  {form.name:<20} {form.median_ms:8.1f} ms/frame")
    fp32, fp32_cl, int8_ms = (form.median_ms for form in forms)
    print(f"  int8 speed-up: {fp32 / int8_ms:.2f}x over fp32, {fp32_cl / int8_ms:.2f}x over fp32 channels_last")
    worst, scale = qat_agreement(qat, int8, frames)
    print(f"  int8 vs fake-quant (QAT) output: max |difference| {worst:.2e} (mean |output| {scale:.3f})")


if __name__ == "__main__":
    main()
