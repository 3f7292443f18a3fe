"""Training checkpoints: everything needed to rebuild a method and to resume its training exactly.

A checkpoint is one ``torch.save`` file holding plain data only (tensors, numbers, strings, lists, dicts), so it
loads with ``torch.load(weights_only=True)`` and never runs pickled code::

    {"format": "denoiser-checkpoint/1",
     "method": {"method", "preset", "scale"},     # Method.config(): rebuilds it through the registry
     "model": state_dict, "optimizer": state_dict | None, "scheduler": state_dict | None,
     "train_config": TrainConfig as a dict | None, "step": int, "epoch": float,
     "rng": [per-rank RNG states] | None, "best_metric": {"name", "value", "step"} | None,
     "extra": {free-form plain data, e.g. the tracking run id}}

Files are written to a temporary name in the same folder and renamed into place (``os.replace``), so a reader,
or a run killed mid-write, never sees half a checkpoint.
"""

from __future__ import annotations

import io
import os
import random
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import torch

from model.methods.base import Method

CHECKPOINT_FORMAT = "denoiser-checkpoint/1"


def capture_rng() -> dict[str, Any]:
    """This process's RNG states (torch CPU and CUDA, NumPy's global, Python's) as plain data."""
    numpy_state = np.random.get_state(legacy=False)
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {"bit_generator": numpy_state["bit_generator"],
                  "key": torch.from_numpy(numpy_state["state"]["key"].astype(np.int64)),
                  "pos": int(numpy_state["state"]["pos"]),
                  "has_gauss": int(numpy_state["has_gauss"]), "gauss": float(numpy_state["gauss"])},
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng(state: dict[str, Any]) -> None:
    """Put back RNG states from ``capture_rng``."""
    torch.set_rng_state(state["torch"])
    numpy_state = state["numpy"]
    np.random.set_state({"bit_generator": numpy_state["bit_generator"],
                         "state": {"key": numpy_state["key"].numpy().astype(np.uint32), "pos": numpy_state["pos"]},
                         "has_gauss": numpy_state["has_gauss"], "gauss": numpy_state["gauss"]})
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | os.PathLike, *, method: Method,
                    optimizer: torch.optim.Optimizer | None = None,
                    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
                    train_config: dict[str, Any] | None = None, step: int = 0, epoch: float = 0.0,
                    rng: list[dict[str, Any]] | None = None, best_metric: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None) -> Path:
    """Write a checkpoint atomically to ``path`` (parent folders are created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    content = {
        "format": CHECKPOINT_FORMAT,
        "method": method.config(),
        # Saved from CPU copies so a checkpoint written on a GPU loads anywhere.
        "model": {name: tensor.detach().cpu() for name, tensor in method.state_dict().items()},
        "optimizer": None if optimizer is None else optimizer.state_dict(),
        "scheduler": None if scheduler is None else scheduler.state_dict(),
        "train_config": train_config,
        "step": int(step),
        "epoch": float(epoch),
        "rng": rng,
        "best_metric": best_metric,
        "extra": dict(extra or {}),
    }
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    # Serialized in memory first: torch.save names the zip's root folder after the file it writes to, so saving
    # straight to a randomly named temporary file made the same weights give different bytes (and sha256) each time.
    buffer = io.BytesIO()
    torch.save(content, buffer)
    try:
        temporary.write_bytes(buffer.getvalue())
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint`` (plain data only: ``weights_only=True``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        content = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises several types for a damaged or foreign file
        # torch's own message is a page of advice about weights_only that does not fit this case: left out.
        raise ValueError(f"{path}: not a readable checkpoint: torch.load cannot read it as saved weights "
                         f"({type(error).__name__}); give a file written by denoiser train "
                         f"(model.training.checkpoint.save_checkpoint)") from None
    if not isinstance(content, dict) or content.get("format") != CHECKPOINT_FORMAT:
        found = content.get("format") if isinstance(content, dict) else type(content).__name__
        raise ValueError(f"{path}: format is {found!r}, expected {CHECKPOINT_FORMAT!r}")
    return content


def load_method(path: str | os.PathLike, device: str | torch.device = "cpu", scale: int | None = None) -> Method:
    """Rebuild the checkpoint's method through the registry, load its weights, and return it in eval mode.

    ``scale`` (None: the checkpoint's own) may differ from the trained scale only for methods whose network
    works at render resolution and upscales its result by interpolation (``denoises_at_render_resolution``):
    a WSKPN trained at 1x is then evaluated as "WSKPN + bicubic" at 2x with the same weights.
    """
    from model.methods.registry import build_method

    content = load_checkpoint(path)
    config = content["method"]
    name = f"{config['method']}:{config['preset']}"
    method = build_method(name, scale=config["scale"])
    if scale is not None and scale != config["scale"]:
        if not method.denoises_at_render_resolution:
            raise ValueError(f"checkpoint {path} holds a scale-{config['scale']} {method.label}, whose network "
                             f"depends on its output scale; it cannot run at scale {scale}")
        method = build_method(name, scale=scale)
    method.load_state_dict(content["model"])
    return method.to(device).eval()
