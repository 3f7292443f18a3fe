"""The ``generate`` job: render scene recipes (model.data.generate) into a stored dataset, creating it if needed.

Each sequence is rendered into the job's own folder (``jobs/<id>/render/<sequence>``) and then moved into the
dataset under the dataset's lock (``core.dataset_lock``, the one uploads take), so the stored dataset
only ever gains complete sequences and never races an upload's manifest change. Sequences already published are
listed in ``jobs/<id>/generated.json``: a job resumed after its worker was lost renders only the rest.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

from model.io.dataset import MANIFEST, Dataset
from core.jobs.specs import GenerateParams
from core.storage import Storage
from workers.tasks.context import JobContext

PUBLISHED_FILE = "generated.json"


def run(context: JobContext) -> dict[str, Any]:
    from model.data.generate import default_sequence_name, generate_sequence
    from model.data.render import RenderSettings

    params = GenerateParams.model_validate(context.params)
    width, height = params.size
    settings = RenderSettings(width=width, height=height, ref_spp=params.ref_spp, ref_scales=tuple(params.scales),
                              albedo_spp=params.albedo_spp, max_depth=params.max_depth, jitter=params.jitter,
                              variant="cuda_ad_rgb" if context.record["device"] == "gpu" else None)
    published_file = context.folder / PUBLISHED_FILE
    published = json.loads(published_file.read_text()) if published_file.is_file() else []
    total = params.frames * len(params.scenes)
    context.baseline = params.frames * len(published)
    for position, scene in enumerate(params.scenes):
        name = default_sequence_name(scene, params.seed)
        if name in published:
            continue
        work = context.folder / "render" / name
        shutil.rmtree(work, ignore_errors=True)  # what a lost worker left half-written
        done_before = position * params.frames

        def on_frame(done: int, frames: int, message: str, offset: int = done_before) -> None:
            context.progress(offset + done, total, message)

        context.logger.info("rendering %s (%d frames at %dx%d, %d spp references)", name, params.frames, width,
                            height, params.ref_spp)
        generate_sequence(scene, work, frames=params.frames, settings=settings, seed=params.seed,
                          split=params.split, name=name, half=params.half, overwrite=True, progress=False,
                          on_frame=on_frame)
        publish(context.storage, params.dataset, work / name, params.split, replace=params.overwrite)
        shutil.rmtree(work, ignore_errors=True)
        published.append(name)
        published_file.write_text(json.dumps(published))
        context.logger.info("added sequence %s to dataset %s", name, params.dataset)
    shutil.rmtree(context.folder / "render", ignore_errors=True)
    return {"dataset": params.dataset, "split": params.split, "sequences": published, "frames_per_sequence":
            params.frames, "resolution": [width, height], "scales": params.scales}


def publish(storage: Storage, dataset_id: str, folder: Path, split: str, *, replace: bool) -> None:
    """Move a finished sequence folder into the stored dataset (created when missing) and register it."""
    from core.dataset_lock import dataset_lock

    name = folder.name
    with dataset_lock(storage, dataset_id):
        root = storage.dataset(dataset_id)
        dataset = Dataset(root) if (root / MANIFEST).is_file() else Dataset.create(root)
        target = root / name
        aside = None
        if target.exists():
            if not replace:
                raise FileExistsError(f"dataset {dataset_id!r} gained a sequence {name!r} while this job ran; "
                                      f"resubmit with another seed or overwrite")
            aside = storage.staging / f"replaced-{name}-{uuid.uuid4().hex[:8]}"
            os.rename(target, aside)
        os.rename(folder, target)
        dataset.add_sequence_dir(name, split, replace=True)
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)
