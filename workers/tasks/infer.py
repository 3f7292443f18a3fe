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

from model.dataset import Sequence, frame_file_name
from service.errors import ApiError
from service.schemas import InferParams
from service.storage import Storage
from workers.tasks.checks import open_dataset, split_sequences
from workers.tasks.context import JobContext
from workers.tasks.methods import check_registry_method, check_rescalable, checkpoint_method, checkpoint_source


def selected_sequences(params: InferParams, storage: Storage) -> list[Sequence]:
    dataset = open_dataset(storage, params.dataset)
    if params.split is not None:
        return split_sequences(dataset, params.dataset, params.split)
    if params.sequences is not None:
        known = set(dataset.names())
        unknown = [name for name in params.sequences if name not in known]
        if unknown:
            raise ApiError(404, "sequence_not_found", f"dataset {params.dataset!r} has no sequence(s) "
                           f"{', '.join(map(repr, unknown))}")
        return [dataset.sequence(name) for name in dict.fromkeys(params.sequences)]
    sequences = dataset.sequences()
    if not sequences:
        raise ApiError(422, "empty_dataset", f"dataset {params.dataset!r} has no sequences")
    return sequences


def check(params: InferParams, storage: Storage) -> dict[str, Any]:
    selected_sequences(params, storage)
    path = checkpoint_source(params.model, storage)
    if path is None:
        check_registry_method(params.model, params.scale or 1)
    else:
        config = checkpoint_method(path, params.model)
        if params.scale is not None and config.get("scale") != params.scale:
            check_rescalable(params.model, config, params.scale)
    return params.model_dump()


def run(context: JobContext) -> dict[str, Any]:
    import torch

    from model.exr import write_image
    from model.methods.base import FrameBatch
    from workers.tasks.methods import build_for_inference

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
