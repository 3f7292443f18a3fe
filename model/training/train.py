"""The training engine: sequence crops unrolled through ``method.step``, Adam, checkpoints, exact resume, DDP.

One step (nanoGPT-style, one ``master_process`` flag guards every log, validation and checkpoint): take this step's
global batch from ``SampleStream`` (rank r of w takes every w-th sample, so w ranks see one process's batch); unroll
each sample's T frames through ``method.step`` from ``state=None``, the state carried; ``SequenceLoss`` (SMAPE per
frame plus L1 on the frame-to-frame change, every frame counted by default: the first is what a method outputs after
every cut); backward, gradient clipping, Adam and the learning-rate schedule.

DDP wraps the method in ``SequenceUnroll``, whose ``forward`` runs the whole unrolled sequence: DistributedDataParallel
only synchronizes gradients of computations through the wrapped module's ``forward``, and methods are driven through
``step``. Exact resume: ``last.pt`` holds the model, optimizer, scheduler, step, every rank's RNG state and the best
validation result, and samples are a function of (seed, epoch, index), so a restarted run sees the batches an
uninterrupted one sees and ends with the same weights (docs/training.md, "Checkpoints and resume"). Tracking goes
through a ``Tracker``; this module never imports MLflow (``core.tracking.MLflowTracker`` implements it).
"""

from __future__ import annotations

import gc
import math
import random
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from model.evaluation import metrics
from model.training.checkpoint import capture_rng, load_checkpoint, restore_rng, save_checkpoint
from model.data.crops import FrameCache, SequenceCrops, collate_crops
from model.io.dataset import Dataset
from model.training.losses import SequenceLoss
from model.methods.base import FrameBatch, Method
from model.methods.registry import build_method, inference_cost
from model.ops.tonemap import display_encode
from model.training.spatial_cache import SpatialEstimateCache
from model.training.training_settings import TrainConfig

LAST_CHECKPOINT = "last.pt"
BEST_CHECKPOINT = "best.pt"
GRID_SAMPLES = 4  # crops shown in the logged noisy / output / reference grid

Progress = Callable[[int, int, str], None]  # (current step, total steps, message)


class Tracker(Protocol):
    """What training reports to (rank 0 only). ``core.tracking.MLflowTracker`` and ``NullTracker`` implement it."""

    @property
    def run_id(self) -> str | None: ...

    def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None: ...

    def log_metrics(self, metrics: dict[str, float], step: int) -> None: ...

    def log_image_grid(self, name: str, columns: dict[str, list[np.ndarray]], step: int) -> None:
        """``columns``: title -> one HxWx3 display-encoded image in [0, 1] per row."""

    def log_dataset(self, path: str, context: str) -> None:
        """Record the dataset folder the run reads (lineage), ``context``: training, evaluation."""

    def log_model(self, checkpoint: Path, registered_name: str, tags: dict[str, str]) -> dict[str, Any] | None:
        """Store the final checkpoint and register it; returns what was registered (name, version), if anything."""

    def finish(self, status: str) -> None:
        """``status``: FINISHED, FAILED or KILLED."""


class NullTracker:
    """Tracks nothing: the default, and what ranks other than 0 use."""

    run_id: str | None = None

    def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None:
        pass

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        pass

    def log_image_grid(self, name: str, columns: dict[str, list[np.ndarray]], step: int) -> None:
        pass

    def log_dataset(self, path: str, context: str) -> None:
        pass

    def log_model(self, checkpoint: Path, registered_name: str, tags: dict[str, str]) -> dict[str, Any] | None:
        return None

    def finish(self, status: str) -> None:
        pass


class SequenceUnroll(nn.Module):
    """Runs a method over T frames in ``forward``, so DistributedDataParallel sees (and syncs) the whole unroll.

    Returns the outputs and the method's auxiliary loss (None if it has none), computed here too because it
    depends on the states of the unroll.
    """

    def __init__(self, method: Method) -> None:
        super().__init__()
        self.method = method

    def forward(self, frames: list[FrameBatch]) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        outputs, states, state = [], [], None
        for frame in frames:
            output, state = self.method.step(frame.without_reference(), state)
            outputs.append(output)
            states.append(state)
        return outputs, self.method.auxiliary_loss(frames, states)


class SampleStream:
    """The order training samples are drawn in: epoch after epoch, each a permutation seeded by (seed, epoch).

    Step k's global batch is positions [k B, (k + 1) B) of the endless stream, so any step's batch is known
    without replaying earlier ones (exact resume), and batches may run across epoch ends (any batch size works,
    even one larger than the split).
    """

    def __init__(self, size: int, seed: int) -> None:
        self.size = size
        self.seed = seed
        self._epoch: int | None = None
        self._order: list[int] = []

    def at(self, position: int) -> tuple[int, int]:
        """(epoch, sample index) at a stream position."""
        epoch, offset = divmod(position, self.size)
        if epoch != self._epoch:
            generator = torch.Generator().manual_seed(_derived_seed(self.seed, epoch))
            self._order = torch.randperm(self.size, generator=generator).tolist()
            self._epoch = epoch
        return epoch, self._order[offset]

    def batch(self, step: int, batch_size: int, rank: int = 0, world_size: int = 1) -> list[tuple[int, int]]:
        """This rank's share of step ``step``'s global batch: every ``world_size``-th sample from ``rank``."""
        first = step * batch_size
        return [self.at(first + position) for position in range(rank, batch_size, world_size)]


def lr_factor(config: TrainConfig, total_steps: int) -> Callable[[int], float]:
    """Multiplier of the base learning rate at each step: linear warm-up, then the configured schedule."""
    warmup = min(config.warmup_steps, total_steps)

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        progress = (step - warmup) / max(1, total_steps - warmup)
        if config.schedule == "cosine":
            return config.min_lr_ratio + (1 - config.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * min(progress, 1)))
        if config.schedule == "step":
            every = config.lr_step_every or max(1, math.ceil((total_steps - warmup) / 3))
            return config.lr_step_gamma ** ((step - warmup) // every)
        return 1.0

    return factor


def resolve_device(name: str, rank: int = 0) -> torch.device:
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("device 'cuda' was asked for, but torch sees no CUDA device")
        return torch.device("cuda", rank % torch.cuda.device_count())
    return torch.device("cpu")


def default_registered_name(method: Method) -> str:
    return f"{method.name}-{method.preset}-x{method.scale}"


def prepare(config: TrainConfig) -> tuple[SequenceCrops, list[FrameCache], Method]:
    """Check the config, open the training and validation data and build the method (seeded), or raise ValueError
    (or KeyError for an unknown method or preset) naming the problem. Cheap: reads one frame per training sequence.
    """
    config.check()
    dataset = Dataset(config.data)
    torch.manual_seed(config.seed)  # the same initial weights in every rank and every run
    method = build_method(config.method, config.scale)
    spatial = SpatialEstimateCache(method.spatial_prior, dataset.root) if method.spatial_prior else None
    crops = SequenceCrops(dataset, config.train_split, config.crop, config.frames_per_sample,
                          scale=config.scale, seed=config.seed, augment=config.augment, spatial=spatial)
    validation = [FrameCache(sequence, config.scale, spatial)
                  for sequence in dataset.sequences(config.validation_split)]
    if not any(p.requires_grad for p in method.parameters()):
        raise ValueError(f"method {method.label!r} has no trainable parameters; only learned methods train")
    if config.init_from:
        _load_initial_weights(method, config.init_from)
    elif config.shipped_settings:
        method.use_shipped_settings()
    return crops, validation, method


def _load_initial_weights(method: Method, path: str) -> None:
    """Start from another checkpoint's weights (a resume from ``out/last.pt`` still takes precedence)."""
    content = load_checkpoint(path)
    source = content["method"]
    if source["method"] != method.name or source["scale"] != method.scale:
        raise ValueError(f"--init-from {path} holds {source['method']}:{source['preset']} at scale {source['scale']}; "
                         f"it cannot initialize {method.label} at scale {method.scale}")
    try:
        method.load_initial_weights(content["model"])
    except (KeyError, RuntimeError) as error:
        message = error.args[0] if error.args else error
        raise ValueError(f"--init-from {path}: its weights do not fit {method.label}: {message}") from None


def resumable_checkpoint(config: TrainConfig, method: Method, total_steps: int) -> dict[str, Any] | None:
    """``out/last.pt`` when training should resume from it (None: start afresh); ValueError when it cannot.

    It cannot when it belongs to another method, preset or scale, or has already reached ``total_steps``.
    """
    last = Path(config.out) / LAST_CHECKPOINT
    if not (config.resume and last.is_file()):
        return None
    checkpoint = load_checkpoint(last)
    if checkpoint["method"] != method.config():
        raise ValueError(f"{last} is a checkpoint of {checkpoint['method']}, not of {method.config()}; "
                         f"use another output folder or turn resume off")
    if checkpoint["step"] >= total_steps:
        raise ValueError(f"{last} is already at step {checkpoint['step']} of {total_steps}; ask for more steps, "
                         f"turn resume off, or use another output folder")
    return checkpoint


def train(config: TrainConfig, tracker: Tracker | None = None, rank: int = 0, world_size: int = 1,
          progress: Progress | None = None, collective_timeout: float | None = None) -> dict[str, Any]:
    """Train ``config.method`` on ``config.data``; returns a summary (steps, losses, validation, checkpoints, run id).

    With ``world_size`` > 1 this is one rank of a DDP job (``workers.ddp`` starts them with MASTER_ADDR/PORT set);
    the process group is created here unless the caller already did. Only rank 0 uses ``tracker`` and
    ``progress``. ``progress`` may raise to stop training; the last checkpoint then stays for a resume.
    ``collective_timeout``: seconds a rank waits in one collective before it fails (None: torch's default).
    """
    if world_size != config.world_size:
        raise ValueError(f"train() called with world_size={world_size} for a config with {config.world_size}")
    device = resolve_device(config.device, rank)
    if config.threads:
        torch.set_num_threads(config.threads)
    own_group = world_size > 1 and not dist.is_initialized()
    if own_group:
        if device.type == "cuda":
            torch.cuda.set_device(device)
        timeout = None if collective_timeout is None else timedelta(seconds=collective_timeout)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=rank, world_size=world_size,
                                timeout=timeout)
    if not own_group:
        return _Training(config, tracker or NullTracker(), rank, world_size, device, progress).run()
    try:
        result = _Training(config, tracker or NullTracker(), rank, world_size, device, progress).run()
        # Tear down only when every rank is done with collectives, and once the DDP wrapper (whose reducer holds
        # the gloo group, kept alive by module reference cycles) is gone: a rank that exits first, or a group
        # freed during interpreter shutdown, aborted the process in gloo's threads about once in 20 jobs.
        gc.collect()
        dist.barrier()
        return result
    finally:
        dist.destroy_process_group()
        gc.collect()


class _Training:
    """One training run's state; ``run`` is the loop. Split into methods only to keep each phase readable."""

    def __init__(self, config: TrainConfig, tracker: Tracker, rank: int, world_size: int, device: torch.device,
                 progress: Progress | None) -> None:
        self.config = config
        self.rank = rank
        self.world_size = world_size
        self.master_process = rank == 0
        self.tracker = tracker if self.master_process else NullTracker()
        self.progress = progress if self.master_process else None
        self.device = device
        self.out = Path(config.out)

        self.crops, self.validation, self.method = prepare(config)
        # Size as the model runs (its inference form): what the registry tags and every report give.
        self.inference_params, self.flops_per_pixel = inference_cost(self.method) if self.master_process else (0, 0.0)
        self.method.to(device).train()
        unroll = SequenceUnroll(self.method)
        # device_ids=None: the module lives on one device and batches are moved there before forward. Every
        # parameter must take part in each unrolled forward (find_unused_parameters=False, DDP's cheaper default).
        self.model = nn.parallel.DistributedDataParallel(unroll) if world_size > 1 else unroll
        self.optimizer = torch.optim.Adam(self.method.parameters(), lr=config.lr)
        self.total_steps = config.total_steps(len(self.crops))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, lr_factor(config, self.total_steps))
        spatial, temporal = self.method.loss_weights
        self.loss = SequenceLoss(spatial if config.spatial_weight is None else config.spatial_weight,
                                 temporal if config.temporal_weight is None else config.temporal_weight,
                                 config.tonemap, config.frame_weights(), display_weight=config.display_weight)
        self.stream = SampleStream(len(self.crops), config.seed)
        self.step = 0
        self.best_metric: dict[str, Any] | None = None
        self.resumed_run_id: str | None = None
        self.resumed_from_step: int | None = None  # the checkpoint's step when this run continued one
        self.last_validation: dict[str, float] | None = None
        self.last_losses: dict[str, float] = {}

    # ------------------------------------------------------------------------------------------ run

    def run(self) -> dict[str, Any]:
        started = time.perf_counter()
        self._resume_or_seed()
        self.tracker.start(self._params(), resume_run_id=self.resumed_run_id)
        try:
            self.tracker.log_dataset(self.config.data, "training")
            self._loop()
            registered = self._finish()
        except BaseException as error:
            self.tracker.finish("KILLED" if isinstance(error, KeyboardInterrupt) else "FAILED")
            raise
        self.tracker.finish("FINISHED")
        return self._result(registered, time.perf_counter() - started)

    def _loop(self) -> None:
        config = self.config
        if self.step == 0 and config.init_from:
            # A fine-tune can end below where it started (too high a learning rate, too little data): with its
            # starting weights validated as step 0, best.pt is never worse on validation than the init.
            self._validate()
        while self.step < self.total_steps:
            frames = self._batch(self.step)
            outputs, auxiliary = self.model(frames)
            terms = self.loss(outputs, [frame.reference for frame in frames], auxiliary)
            self.optimizer.zero_grad(set_to_none=True)
            terms.total.backward()
            grad_norm = self._clip_gradients()
            self.optimizer.step()
            lr = self.optimizer.param_groups[0]["lr"]
            self.scheduler.step()
            self.step += 1

            self.last_losses = self._global_losses(terms)
            self.tracker.log_metrics({**{f"train/{k}": v for k, v in self.last_losses.items()},
                                      "train/lr": lr, "train/grad_norm": grad_norm, "train/epoch": self.epoch},
                                     self.step)
            final = self.step == self.total_steps
            if final or (config.validate_every and self.step % config.validate_every == 0):
                self._validate_and_log(frames, outputs)
            if final or (config.checkpoint_every and self.step % config.checkpoint_every == 0):
                self._save_last()
            if self.progress is not None:
                self.progress(self.step, self.total_steps, self._progress_message())

    @property
    def epoch(self) -> float:
        return self.step * self.config.batch / len(self.crops)

    def _batch(self, step: int) -> list[FrameBatch]:
        picks = self.stream.batch(step, self.config.batch, self.rank, self.world_size)
        frames = collate_crops([self.crops.sample(index, epoch) for epoch, index in picks])
        return [frame.to(self.device) for frame in frames]

    def _clip_gradients(self) -> float:
        parameters = [p for p in self.method.parameters() if p.grad is not None]
        if self.config.grad_clip > 0:
            return float(nn.utils.clip_grad_norm_(parameters, self.config.grad_clip))
        return float(torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in parameters]))) if parameters else 0.0

    def _global_losses(self, terms) -> dict[str, float]:
        values = terms.detached()
        if self.world_size == 1:
            return values
        # Each rank's loss is the mean over its share of the batch; the global batch's loss is their mean.
        packed = torch.tensor(list(values.values()), dtype=torch.float64, device=self.device)
        dist.all_reduce(packed)
        return dict(zip(values, (packed / self.world_size).tolist(), strict=True))

    def _progress_message(self) -> str:
        message = f"step {self.step}/{self.total_steps}, loss {self.last_losses['loss']:.4f}"
        if self.last_validation is not None:
            message += f", validation PSNR {self.last_validation['psnr']:.2f} dB"
        return message

    # ------------------------------------------------------------------------- validation, images

    def _validate_and_log(self, frames: list[FrameBatch], outputs: list[torch.Tensor]) -> None:
        if not self.master_process:
            return
        self.tracker.log_image_grid(f"samples/step_{self.step:07d}.png", _sample_grid(frames[-1], outputs[-1]),
                                    self.step)
        self._validate()

    def _validate(self) -> None:
        """Validate the weights as they are now; a new best is written to best.pt (master process only)."""
        if not self.master_process or not self.validation:
            return
        self.last_validation = validate(self.method, self.validation, self.device, self.config.validation_frames)
        self.tracker.log_metrics({f"validation/{k}": v for k, v in self.last_validation.items()}, self.step)
        psnr = self.last_validation["psnr"]
        if self.best_metric is None or psnr > self.best_metric["value"]:
            self.best_metric = {"name": "validation/psnr", "value": psnr, "step": self.step}
            self._write_checkpoint(self.out / BEST_CHECKPOINT, rng=None)

    # ------------------------------------------------------------------------- checkpoints, resume

    def _save_last(self) -> None:
        rng = capture_rng()
        if self.world_size > 1:  # every rank's RNG, so each rank resumes its own random stream
            states: list[Any] = [None] * self.world_size
            dist.all_gather_object(states, rng)
        else:
            states = [rng]
        if self.master_process:
            self._write_checkpoint(self.out / LAST_CHECKPOINT, rng=states)

    def _write_checkpoint(self, path: Path, rng: list[dict[str, Any]] | None) -> None:
        save_checkpoint(path, method=self.method, optimizer=self.optimizer, scheduler=self.scheduler,
                        train_config=self.config.to_dict(), step=self.step, epoch=self.epoch, rng=rng,
                        best_metric=self.best_metric,
                        extra={"tracking_run_id": self.tracker.run_id, "total_steps": self.total_steps})

    def _resume_or_seed(self) -> None:
        checkpoint = resumable_checkpoint(self.config, self.method, self.total_steps)
        if checkpoint is None:
            _seed_everything(_derived_seed(self.config.seed, self.rank, 0))
            return
        parameters = [id(parameter) for parameter in self.method.parameters()]
        self.method.load_state_dict(checkpoint["model"])
        if [id(parameter) for parameter in self.method.parameters()] != parameters:
            # A method that rebuilds itself to fit older weights (fused before its running-mean candidate) would
            # leave the optimizer holding the parameters it replaced.
            raise ValueError(f"{self.out / LAST_CHECKPOINT} holds an older network of {self.method.label} than "
                             f"this version trains; continue from it with --init-from and a new --out")
        self.optimizer.load_state_dict(checkpoint["optimizer"])
        self.scheduler.load_state_dict(checkpoint["scheduler"])
        self.step = self.resumed_from_step = checkpoint["step"]
        self.best_metric = checkpoint["best_metric"]
        self.resumed_run_id = checkpoint["extra"].get("tracking_run_id")
        rng = checkpoint["rng"]
        if rng is not None and len(rng) == self.world_size:
            restore_rng(rng[self.rank])
        else:  # resumed with another number of ranks: a fresh but still seeded stream per rank
            _seed_everything(_derived_seed(self.config.seed, self.rank, self.step))

    # -------------------------------------------------------------------------------- the end

    def _params(self) -> dict[str, Any]:
        return {**self.config.to_dict(), "method_name": self.method.name, "preset": self.method.preset,
                "parameters": self.inference_params, "trainable_parameters": self.method.parameter_count(),
                "flops_per_pixel": self.flops_per_pixel, "total_steps": self.total_steps,
                "train_samples": len(self.crops), "unused_train_sequences": len(self.crops.unused),
                "validation_sequences": len(self.validation), "device": str(self.device),
                **{f"setting.{name}": value for name, value in self.method.run_time_settings().items()}}

    def _finish(self) -> dict[str, Any] | None:
        if not self.master_process:
            return None
        tags = {"method": self.method.name, "preset": self.method.preset, "scale": str(self.method.scale),
                "params": str(self.inference_params), "flops_per_pixel": f"{self.flops_per_pixel:.6g}",
                "steps": str(self.step)}
        if self.last_validation is not None:
            tags["validation_psnr"] = f"{self.last_validation['psnr']:.4f}"
        name = self.config.register_as or default_registered_name(self.method)
        return self.tracker.log_model(self.out / LAST_CHECKPOINT, name, tags)

    def _result(self, registered: dict[str, Any] | None, seconds: float) -> dict[str, Any]:
        best = self.out / BEST_CHECKPOINT
        return {"rank": self.rank, "steps": self.step, "epochs": self.epoch, "losses": self.last_losses,
                "validation": self.last_validation, "best_metric": self.best_metric,
                "checkpoint": str(self.out / LAST_CHECKPOINT),
                "best_checkpoint": str(best) if best.is_file() else None,
                "run_id": self.tracker.run_id, "registered_model": registered,
                "resumed_from_step": self.resumed_from_step,
                "parameters": self.inference_params, "trainable_parameters": self.method.parameter_count(),
                "flops_per_pixel": self.flops_per_pixel, "seconds": seconds,
                "unused_sequences": [{"name": name, "longest_run": frames} for name, frames in self.crops.unused]}


@torch.no_grad()
def validate(method: Method, sequences: list[FrameCache], device: torch.device,
             max_frames: int | None = None) -> dict[str, float]:
    """The protocol's PSNR (display-encoded), SMAPE (linear HDR) and temporal error (``model.evaluation.metrics``) on whole
    sequences: per frame, averaged per sequence, then over sequences. The method runs from ``state=None`` through
    each sequence, dropping history at its cuts. The temporal error is left out when no sequence has two frames."""
    was_training = method.training
    method.eval()
    per_sequence: dict[str, list[float]] = {"psnr": [], "smape": [], "temporal_error": []}
    for sequence in sequences:
        state = None
        outputs, references, cuts = [], [], []
        for index in range(min(len(sequence), max_frames or len(sequence))):
            frame = sequence[index].to(device)
            output, state = method.step(frame.without_reference(), state)
            outputs.append(output[0].cpu())
            references.append(frame.reference[0].cpu())
            cuts.append(bool(frame.camera_cut[0]))
        outputs_t, references_t = torch.stack(outputs), torch.stack(references)
        per_sequence["psnr"].append(float(metrics.psnr(display_encode(outputs_t), display_encode(references_t)).mean()))
        per_sequence["smape"].append(float(metrics.smape(outputs_t, references_t).mean()))
        temporal = metrics.temporal_error(outputs_t, references_t, cuts)
        if temporal is not None:
            per_sequence["temporal_error"].append(temporal)
    method.train(was_training)
    return {name: float(np.mean(values)) for name, values in per_sequence.items() if values}


def _sample_grid(frame: FrameBatch, output: torch.Tensor) -> dict[str, list[np.ndarray]]:
    def images(tensor: torch.Tensor) -> list[np.ndarray]:
        encoded = display_encode(tensor[:GRID_SAMPLES].detach().float()).cpu()
        return [image.permute(1, 2, 0).numpy() for image in encoded]

    return {"noisy": images(frame.color), "output": images(output), "reference": images(frame.reference)}


def _derived_seed(*parts: int) -> int:
    """A 63-bit seed from integers, well mixed (NumPy's SeedSequence), e.g. (seed, rank, step)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def _seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)
