"""The ``infer`` job: run a model over stored sequences (``model.deployment.infer``), one EXR per output frame.

Outputs go to ``results/<job id>/<sequence>/frame_NNNN.exr``, written atomically, so a listing never shows half a
file. An execution after a lost worker starts over (outputs are deterministic; the folder is cleared first).
"""

from __future__ import annotations

import shutil
from typing import Any

from core.jobs.infer import selected_sequences
from core.jobs.specs import InferParams
from workers.tasks.context import JobContext


def run(context: JobContext) -> dict[str, Any]:
    import torch

    from core.jobs.methods import build_for_inference
    from model.deployment.infer import infer_sequences

    params = InferParams.model_validate(context.params)
    sequences = selected_sequences(params, context.storage)
    device = torch.device(context.torch_device)
    method = build_for_inference(params.model, params.scale, context.storage).to(device)
    context.logger.info("running %s (scale %d) over %d sequences", method.label, method.scale, len(sequences))
    out = context.storage.result(context.job_id)
    shutil.rmtree(out, ignore_errors=True)
    run = infer_sequences(method, sequences, out, device, on_frame=context.progress)
    return {
        "dataset": params.dataset, "model": params.model,
        "method": {"label": method.label, "method": method.name, "preset": method.preset, "scale": method.scale,
                   "params": method.parameter_count()},
        "sequences": [{"name": s.name, "frames": len(s)} for s in sequences], "frames": run["frames"],
        "ms_per_frame": run["ms_per_frame"],
        "device": str(device), "threads": torch.get_num_threads(),
        "results": f"/jobs/{context.job_id}/results", "zip": f"/jobs/{context.job_id}/results.zip",
    }
