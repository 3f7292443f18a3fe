"""The ``infer`` job: run a model over stored sequences, history carried frame to frame, one EXR per output frame.

Outputs go to ``results/<job id>/<sequence>/frame_NNNN.exr`` (one-part float32 R,G,B at the model's output
resolution, header attributes ``frame_index``, ``sequence`` and ``scale``), written atomically, so a listing never
shows half a file. Each sequence starts from ``state=None``; camera cuts are flagged in the frames and honoured by
the method, as in sessions and evaluation. An execution after a lost worker starts over (outputs are
deterministic; the folder is cleared first).
"""

from __future__ import annotations

import shutil
import statistics
import time
from typing import Any

from model.io.dataset import frame_file_name
from core.jobs.infer import selected_sequences
from core.jobs.specs import InferParams
from workers.tasks.context import JobContext


def run(context: JobContext) -> dict[str, Any]:
    import torch

    from model.io.exr import write_image
    from model.methods.base import FrameBatch
    from core.jobs.methods import build_for_inference

    params = InferParams.model_validate(context.params)
    sequences = selected_sequences(params, context.storage)
    device = torch.device(context.torch_device)
    method = build_for_inference(params.model, params.scale, context.storage).to(device)
    context.logger.info("running %s (scale %d) over %d sequences", method.label, method.scale, len(sequences))
    out = context.storage.result(context.job_id)
    shutil.rmtree(out, ignore_errors=True)
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
            context.progress(done, total, f"{sequence.name}: frame {index + 1}/{len(sequence)}")
    return {
        "dataset": params.dataset, "model": params.model,
        "method": {"label": method.label, "method": method.name, "preset": method.preset, "scale": method.scale,
                   "params": method.parameter_count()},
        "sequences": [{"name": s.name, "frames": len(s)} for s in sequences], "frames": total,
        "ms_per_frame": 1000 * statistics.median(step_seconds) if step_seconds else None,
        "device": str(device), "threads": torch.get_num_threads(),
        "results": f"/jobs/{context.job_id}/results", "zip": f"/jobs/{context.job_id}/results.zip",
    }
