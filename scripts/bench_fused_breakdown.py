"""Where a fused model's step spends its time, OIDN apart: each sub-step of ``Fused.step`` timed on its own.

    .venv/bin/python scripts/bench_fused_breakdown.py --model fused-balanced-x1 --size 512 --size 1920x1080
    .venv/bin/python scripts/bench_fused_breakdown.py --model fused-fast-x1 --size 512 --forms off --forms measured
    .venv/bin/python scripts/bench_fused_breakdown.py --compile-times 256 320 384   # seconds of each frame

The model is loaded as sessions load it (``for_inference`` and the inference-form table named by ``--forms``:
``measured``, ``off`` or a table path; several ``--forms`` run interleaved, frame by frame, in one process, so a
busy machine slows them alike). Every function ``model.methods.fused`` calls by name (the ops, OIDN, the network)
is wrapped with a timer for the run; a step's time less OIDN's is the learned part. A timer would break a compiled
graph, so with a ``compile-step`` form among the tables only OIDN and the network are timed (both run outside the
graph). Prints a markdown table per size: the median ms per frame of each sub-step and of the step, and the first
frame (warm-up; with a compiled form, its compilation) apart. ``--compile-times SIZE ...`` instead steps three
frames at each size in turn with the step compiled (``compile-step+bf16``) and prints each frame's seconds: what
compiling costs at a first and at a later resolution.
"""

from __future__ import annotations

import argparse
import collections
import copy
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="fused-balanced-x1", help="pretrained fused model (default %(default)s)")
    parser.add_argument("--size", action="append", default=[], help="render size WxH or N (repeat; default 512)")
    parser.add_argument("--forms", action="append", default=[], help="inference-form table(s) (default measured)")
    parser.add_argument("--frames", type=int, default=4, help="timed frames after one warm-up (default 4)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--compile-times", nargs="+", type=int, metavar="SIZE",
                        help="print the seconds of three compiled-step frames at each size in turn")
    return parser.parse_args()


class SubStepTimers:
    """Wraps the names ``module`` calls with timers that add up seconds per name while ``active``."""

    def __init__(self, module, names: list[str]) -> None:
        self.seconds: dict[str, float] = collections.defaultdict(float)
        self.depth = 0
        for name in names:
            setattr(module, name, self._timed(name, getattr(module, name)))

    def _timed(self, name: str, function):
        def wrapper(*args, **kwargs):
            # nested calls (an op calling another wrapped op) count in the outer one only
            self.depth += 1
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.depth -= 1
                if self.depth == 0:
                    self.seconds[name] += time.perf_counter() - start
        return wrapper


def main() -> None:
    args = parse_args()
    import numpy as np
    import torch

    import model.methods.fused as fused
    from model.deployment.inference_forms import load_form_table, with_inference_forms
    from model.deployment.malloc import tune_for_large_frames
    from model.deployment.pretrained import load_pretrained
    from model.io.synthetic import moving_pattern_frames
    from model.methods.base import FrameBatch

    torch.set_num_threads(args.threads)
    tune_for_large_frames()
    if args.compile_times:
        compile_times(args.model, args.compile_times)
        return
    names = [name for name, value in vars(fused).items()
             if callable(value) and not isinstance(value, type) and name[0] != "_"
             and getattr(value, "__module__", "").startswith("model.")
             and name not in {"register", "head_candidates", "frame_samples", "frame_of_sample_mean"}]
    names += ["_features", "_upsample_values", "_upsample_mask"]
    forms = args.forms or ["measured"]
    tables = {spec: load_form_table(spec) for spec in forms}
    compiled = any(table is not None and any(row.get("chosen", "").startswith("compile-step")
                                             for rows in table.data["methods"].values() for row in rows.values())
                   for table in tables.values())
    timers = SubStepTimers(fused, ["oidn_denoise"] if compiled else names)
    net_seconds = collections.defaultdict(float)
    methods = {}
    for spec in forms:
        method = load_pretrained(args.model).eval().for_inference()
        forward = method.net.forward

        def timed_forward(*inputs, _forward=forward, _spec=spec):
            start = time.perf_counter()
            try:
                return _forward(*inputs)
            finally:
                net_seconds[_spec] += time.perf_counter() - start
        method.net.forward = timed_forward
        methods[spec] = with_inference_forms(method, tables[spec])
    print(f"{args.model}; {args.threads} torch threads; median ms per frame over {args.frames} frames after one "
          f"warm-up; forms interleaved frame by frame\n")
    for size in args.size or ["512"]:
        width, _, height = size.lower().partition("x")
        render = (int(width), int(height or width))
        batches = [FrameBatch.from_bundles([bundle], scale=None)
                   for bundle in moving_pattern_frames(args.frames + 1, render, np.random.default_rng(0))]
        per_form = {spec: collections.defaultdict(list) for spec in forms}
        states = dict.fromkeys(forms)
        first = {}
        with torch.inference_mode():
            for index, batch in enumerate(batches):
                for spec in forms:
                    timers.seconds.clear()
                    net_seconds.clear()
                    start = time.perf_counter()
                    _, states[spec] = methods[spec].step(copy.copy(batch), states[spec])
                    total = time.perf_counter() - start
                    if index == 0:
                        first[spec] = total
                        continue
                    rows = per_form[spec]
                    for name, seconds in timers.seconds.items():
                        rows[name].append(seconds)
                    rows["network (FusionNet.forward)"].append(net_seconds[spec])
                    rows["step"].append(total)
                    rows["learned part (step - OIDN)"].append(total - timers.seconds.get("oidn_denoise", 0.0))
        print(f"### {render[0]}x{render[1]}\n")
        print("| sub-step | " + " | ".join(forms) + " |")
        print("|---|" + "---:|" * len(forms))
        keys = sorted({key for rows in per_form.values() for key in rows},
                      key=lambda key: -statistics.median(per_form[forms[0]].get(key, [0.0])))
        for key in keys:
            cells = [f"{1000 * statistics.median(per_form[spec][key]):.1f}" if per_form[spec].get(key) else "-"
                     for spec in forms]
            print(f"| {key} | " + " | ".join(cells) + " |")
        print("| first frame (warm-up) | " + " | ".join(f"{1000 * first[spec]:.0f}" for spec in forms) + " |\n")


def compile_times(model: str, sizes: list[int]) -> None:
    import numpy as np
    import torch

    from model.deployment.inference_forms import run_networks_as
    from model.deployment.pretrained import load_pretrained
    from model.io.synthetic import moving_pattern_frames
    from model.methods.base import FrameBatch

    method = load_pretrained(model).eval().for_inference()
    with torch.inference_mode(), run_networks_as(method, "compile-step+bf16"):
        for size in sizes:
            state, seconds = None, []
            for bundle in moving_pattern_frames(3, size, np.random.default_rng(0)):
                start = time.perf_counter()
                _, state = method.step(FrameBatch.from_bundles([bundle], scale=None), state)
                seconds.append(f"{time.perf_counter() - start:.2f}")
            print(f"{size}x{size}: seconds per frame {', '.join(seconds)}", flush=True)
    print(f"compilation failed: {method._compiled_step.failure}" if method._compiled_step.failure else "compiled")


if __name__ == "__main__":
    main()
