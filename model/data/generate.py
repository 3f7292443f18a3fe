"""The dataset generator: renders named scene recipes into sequences of a dataset on disk.

`generate_sequence` is what the CLI (`denoiser generate`) and, later, the dataset-generation job call.
A sequence appears in the dataset only once all of its frames are written (see `SequenceWriter`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from model.data.render import RenderSettings, SceneRenderer
from model.data.scenes import SCENES, build_scene
from model.io.dataset import SPLITS, Dataset, SequenceWriter

ProgressCallback = Callable[[int, int, str], None]


def default_sequence_name(scene: str, seed: int) -> str:
    return f"{scene}_s{seed}"


def generate_sequence(scene: str, out: str | Path, *, frames: int = 16, settings: RenderSettings | None = None,
                      seed: int = 0, split: str = "train", name: str | None = None, half: bool = False,
                      overwrite: bool = False, progress: bool = True,
                      on_frame: ProgressCallback | None = None) -> Path:
    """Render `frames` frames of the recipe `scene` into dataset `out` as one sequence; returns its folder.

    Deterministic for (`scene`, `seed`, `frames`, `settings`). `on_frame(done, total, message)` is called after
    every frame (for job progress); `progress` shows a progress bar on stderr.
    """
    if scene not in SCENES:
        raise KeyError(f"unknown scene {scene!r}; known scenes: {', '.join(sorted(SCENES))}")
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    settings = settings or RenderSettings()
    name = name or default_sequence_name(scene, seed)
    dataset = Dataset.open_or_create(out)
    animation = build_scene(scene, seed, frames)
    renderer = SceneRenderer(animation, settings, seed)
    metadata = {"renderer": "mitsuba3", "variant": renderer.mi.variant(), "seed": seed,
                "ref_spp": settings.ref_spp, "albedo_spp": settings.albedo_spp, "max_depth": settings.max_depth,
                "rr_depth": settings.rr_depth,
                "reconstruction_filter": "box",
                "jitter": "halton(2,3) of frame_index+1, minus 0.5" if settings.jitter else "none (pixel centres)",
                "cuts": sorted(animation.cuts)}
    started = time.perf_counter()
    with SequenceWriter(dataset.root / name, name, scene=scene, metadata=metadata, half=half,
                        overwrite=overwrite) as writer:
        bar = tqdm(total=frames, desc=f"{name}", unit="frame", disable=not progress, leave=True)
        for index in range(frames):
            frame = renderer.render_frame(index)
            frame.sequence = name
            writer.add(frame)
            bar.update(1)
            if on_frame is not None:
                on_frame(index + 1, frames, f"rendered frame {index + 1}/{frames} of {name}")
        bar.close()
    dataset.add_sequence_dir(name, split, replace=overwrite)
    elapsed = time.perf_counter() - started
    if progress:
        print(f"{name}: {frames} frames at {settings.width}x{settings.height}, references x"
              f"{','.join(str(s) for s in settings.ref_scales)} at {settings.ref_spp} spp in {elapsed:.1f} s")
    return dataset.root / name
