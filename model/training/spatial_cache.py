"""OIDN's output per stored frame, computed once and kept: what training feeds methods built on a spatial denoiser.

The `fused` family runs OIDN on every frame before its own network. In training, the same stored frames are
cropped again and again, and OIDN on a frame costs more than the network's training step; so the full frame
is denoised once, the result kept on disk, and crops take their part of it
(`model.data.crops`). OIDN on the full frame is also what inference computes (a crop would see other borders).

The key is the frame's content (color, albedo, specular albedo, normal: what OIDN reads), OIDN's version and
the quality, so a changed frame, another OIDN or another preset never reuses a stale result. Files live in
`<dataset>/.cache/spatial/`; when that folder cannot be written the results stay in memory only.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import logging
import os
import uuid
from pathlib import Path

import numpy as np
import torch

from model.methods.base import FrameBatch
from model.methods.oidn import QUALITIES, oidn_denoise

__all__ = ["SpatialEstimateCache", "oidn_version"]

log = logging.getLogger(__name__)
CACHE_FOLDER = Path(".cache") / "spatial"


def oidn_version() -> str:
    return importlib.metadata.version("pyoidn")


class SpatialEstimateCache:
    """`estimate(frame)`: OIDN at `quality` of a batch-1 frame, from memory, disk, or computed and stored."""

    def __init__(self, quality: str, root: str | Path | None = None) -> None:
        if quality not in QUALITIES:
            raise KeyError(f"OIDN has no quality {quality!r}; qualities: {', '.join(QUALITIES)}")
        self.quality = quality
        self.folder = Path(root) / CACHE_FOLDER if root is not None else None
        self._memory: dict[str, torch.Tensor] = {}
        self.computed = 0  # how many frames OIDN actually ran on (the rest came from the cache)

    def key(self, frame: FrameBatch) -> str:
        digest = hashlib.sha256(f"oidn {oidn_version()} {self.quality}".encode())
        for tensor in (frame.color, frame.albedo, frame.specular_albedo, frame.normal):
            if tensor is not None:
                digest.update(np.ascontiguousarray(tensor.detach().cpu().numpy(), dtype=np.float32).tobytes())
        return digest.hexdigest()

    def estimate(self, frame: FrameBatch) -> torch.Tensor:
        if frame.batch_size != 1:
            raise ValueError(f"the spatial cache holds single frames, got a batch of {frame.batch_size}")
        key = self.key(frame)
        if key in self._memory:
            return self._memory[key]
        path = self.folder / f"{key}.npy" if self.folder is not None else None
        result = None
        if path is not None and path.is_file():
            try:
                result = torch.from_numpy(np.load(path))
            except (OSError, ValueError) as error:  # a torn or foreign file: recompute it
                log.warning("spatial cache: ignoring unreadable %s (%s)", path, error)
        if result is None or result.shape != frame.color.shape:
            result = oidn_denoise(frame.to("cpu"), self.quality)
            self.computed += 1
            if path is not None:
                self._store(path, result)
        self._memory[key] = result
        return result

    def _store(self, path: Path, result: torch.Tensor) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            # A name of this writer's own: training runs side by side share the cache and write the same frames.
            temporary = path.with_name(f"{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp.npy")
            np.save(temporary, result.numpy())
            temporary.replace(path)  # atomic: a reader never sees half a file
        except OSError as error:
            log.warning("spatial cache: cannot write %s (%s); keeping results in memory", path, error)
            self.folder = None
