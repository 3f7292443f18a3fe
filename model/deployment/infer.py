"""Run a method over stored sequences, its history carried frame to frame, one EXR per output frame.

Outputs go to ``OUT/<sequence>/frame_NNNN.exr`` (one-part float32 R,G,B at the method's output resolution, header
attributes ``frame_index``, ``sequence`` and ``scale``). Each sequence starts from ``state=None``; camera cuts are
flagged in the frames and honoured by the method, as in sessions and evaluation. The ``infer`` job and
``denoiser infer`` both run this.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from model.deployment.inference_forms import FormTable, load_form_table, with_inference_forms
from model.io.dataset import Sequence, frame_file_name
from model.io.exr import write_image
from model.methods.base import FrameBatch, Method

OnFrame = Callable[[int, int, str], None]  # (frames done, frames in all, message)


def infer_sequences(method: Method, sequences: list[Sequence], out: str | os.PathLike,
                    device: torch.device | str = "cpu", on_frame: OnFrame | None = None,
                    inference_forms: FormTable | str | None = "measured") -> dict:
    """Every frame of ``sequences`` through ``method`` (ready for inference, on ``device``) in the inference form
    sessions run (``model.deployment.inference_forms``; "off": fp32 eager); returns the frame count and the median
    ms of a step."""
    device = torch.device(device)
    method = with_inference_forms(method, load_form_table(inference_forms), device)
    out = Path(out)
    total = sum(len(s) for s in sequences)
    done = 0
    step_seconds: list[float] = []
    for sequence in sequences:
        folder = out / sequence.name
        folder.mkdir(parents=True, exist_ok=True)
        state = None
        for index in range(len(sequence)):
            frame = FrameBatch.from_bundles([sequence[index]], scale=None).to(device)
            with torch.inference_mode():
                started = time.perf_counter()
                output, state = method.step(frame, state)
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                step_seconds.append(time.perf_counter() - started)
            image = output[0].permute(1, 2, 0).float().cpu().numpy()
            write_image(folder / frame_file_name(index), image,
                        {"frame_index": index, "sequence": sequence.name, "scale": method.scale})
            done += 1
            if on_frame is not None:
                on_frame(done, total, f"{sequence.name}: frame {index + 1}/{len(sequence)}")
    return {"frames": total, "ms_per_frame": 1000 * statistics.median(step_seconds) if step_seconds else None}
