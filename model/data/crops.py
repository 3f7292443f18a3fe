"""Training samples: random crops of T consecutive frames of a dataset split, with flips, brightness changes and
a random rotation of the world frame the normals are given in.

A sample is a window of ``frames`` consecutive frames of one sequence, cropped to ``crop_size`` x ``crop_size``
render pixels at one random position (the same for every frame of the window, so motion vectors still point at
the right history) and, at output scale s, the matching (s * crop_size)^2 crops of the target-resolution buffers
(the reference and, where the data has them, the reference albedos) at s * the offset: render pixel (x, y) covers
reference pixels [s x, s x + s) x [s y, s y + s), so the two crops show the same part of the image. A window
never spans a camera cut: its frames after the first are all continuations, and its first frame is marked as a
cut, because the method starts the sample without history.

Every random choice of sample ``index`` in epoch ``epoch`` (crop position, flips, brightness, rotation) comes from a
generator seeded with (seed, epoch, index), so a sample is the same whichever process, worker or resumed run
asks for it; that is what makes resumed and distributed training reproduce an uninterrupted single process.

Decoded frames are kept in memory (``FrameCache``): the datasets this project trains on are small (tens of
sequences of tens of frames at about 128x128, roughly 2 MB a frame with every buffer), and decoding EXR for each
crop would cost far more than the training step on the 2-core CPU. Larger datasets would need an on-disk
tensor cache instead.
"""

from __future__ import annotations

import math
import os
from dataclasses import fields

import numpy as np
import torch

from model.io.dataset import Dataset, Sequence
from model.io.frames import TARGET_FIELDS
from model.methods.base import FrameBatch
from model.training.spatial_cache import SpatialEstimateCache

# Radiance buffers scaled by the brightness augmentation. Albedos (the reference albedos too) are reflectances in
# [0, 1] and do not change with the light's strength; motion, depth and normals are geometry.
RADIANCE_BUFFERS = ("color", "diffuse", "specular", "reference", "spatial_estimate")
# FrameBatch fields at the output resolution (s times the render resolution): cropped at s times the offset.
TARGET_BUFFERS = tuple(TARGET_FIELDS)
BRIGHTNESS_RANGE = (0.5, 2.0)  # brightness factor, drawn log-uniformly so 0.5x and 2x are equally likely


class FrameCache:
    """One sequence's frames as batch-1 CPU ``FrameBatch`` es (reference at ``scale``), decoded on first use, kept.

    With a ``spatial`` cache, each frame also carries its ``spatial_estimate`` (OIDN of the whole stored frame).
    """

    def __init__(self, sequence: Sequence, scale: int, spatial: SpatialEstimateCache | None = None) -> None:
        if scale not in sequence.scales:
            raise ValueError(f"sequence '{sequence.name}' ({sequence.path}) has no reference at scale {scale} "
                             f"(scales present: {', '.join(str(s) for s in sequence.scales) or 'none'})")
        self.sequence = sequence
        self.scale = scale
        self.spatial = spatial
        self._frames: dict[int, FrameBatch] = {}

    @property
    def name(self) -> str:
        return self.sequence.name

    def __len__(self) -> int:
        return len(self.sequence)

    def __getitem__(self, index: int) -> FrameBatch:
        if index not in self._frames:
            frame = FrameBatch.from_bundles([self.sequence[index]], scale=self.scale)
            if self.spatial is not None:
                frame.spatial_estimate = self.spatial.estimate(frame)
            self._frames[index] = frame
        return self._frames[index]


def sample_windows(cuts: list[int], length: int, frames: int) -> list[int]:
    """First frames of every window of ``frames`` consecutive frames that holds no cut after its first frame.

    A cut at frame c means frames c-1 and c belong to different shots, so a window may start at a cut but must
    not contain one further in.
    """
    cut_set = set(cuts)
    return [start for start in range(length - frames + 1)
            if not any(start + offset in cut_set for offset in range(1, frames))]


def longest_run(cuts: list[int], length: int) -> int:
    """Frames in the longest run of a sequence without a cut: the most frames a sample of it can hold."""
    bounds = sorted({0, length, *(cut for cut in cuts if 0 < cut < length)})
    return max(end - start for start, end in zip(bounds, bounds[1:], strict=False)) if length else 0


class SequenceCrops(torch.utils.data.Dataset):
    """Training samples of one split: ``len(self)`` windows, each a random crop re-drawn every epoch.

    ``self[index]`` (in the epoch set by ``set_epoch``) or ``sample(index, epoch)`` returns a dict of tensors
    stacked over time: image buffers (T, C, h, w), ``jitter`` (T, 2), ``camera_cut`` (T,); ``collate_crops``
    turns a list of them into T batched ``FrameBatch`` es.
    """

    def __init__(self, dataset: Dataset | str | os.PathLike, split: str, crop_size: int, frames: int,
                 scale: int = 1, seed: int = 0, augment: bool = True,
                 spatial: SpatialEstimateCache | None = None) -> None:
        if crop_size < 1 or frames < 1:
            raise ValueError(f"crop size ({crop_size}) and frames per sample ({frames}) must be positive")
        self.dataset = dataset if isinstance(dataset, Dataset) else Dataset(dataset)
        self.split = split
        self.crop_size = crop_size
        self.frames = frames
        self.scale = scale
        self.seed = seed
        self.augment = augment
        self.epoch = 0

        sequences = self.dataset.sequences(split)
        if not sequences:
            raise ValueError(f"dataset {self.dataset.root} has no sequences in split '{split}'")
        for sequence in sequences:
            if sequence.width < crop_size or sequence.height < crop_size:
                raise ValueError(f"sequence '{sequence.name}' is {sequence.width}x{sequence.height}, smaller than "
                                 f"the {crop_size}x{crop_size} crop; use a smaller crop size")
        self.caches = [FrameCache(sequence, scale, spatial) for sequence in sequences]
        self.windows = [(position, start) for position, sequence in enumerate(sequences)
                        for start in sample_windows(sequence.cuts, len(sequence), frames)]
        if not self.windows:
            raise ValueError(f"no sequence of split '{split}' in {self.dataset.root} has {frames} consecutive "
                             f"frames without a camera cut; use fewer frames per sample")
        # Sequences too short for a sample are not trained on; said, since a user's data may be shot by shot.
        sampled = {position for position, _ in self.windows}
        self.unused = tuple((sequence.name, longest_run(sequence.cuts, len(sequence)))
                            for position, sequence in enumerate(sequences) if position not in sampled)
        self.buffers = self._common_buffers()

    def unused_note(self, shown: int = 5) -> str | None:
        """One line naming the sequences no sample comes from (None when every sequence is sampled)."""
        if not self.unused:
            return None
        named = ", ".join(f"{name} ({frames})" for name, frames in self.unused[:shown])
        more = f" and {len(self.unused) - shown} more" if len(self.unused) > shown else ""
        return (f"{len(self.unused)} of {len(self.caches)} sequences of split '{self.split}' hold fewer than "
                f"{self.frames} consecutive frames without a camera cut and are not trained on (their longest run "
                f"in brackets): {named}{more}; fewer frames per sample would use them")

    def _common_buffers(self) -> tuple[str, ...]:
        # An optional buffer (diffuse, roughness, ...) is kept only when every sequence of the split has it, so
        # all batches have the same fields whatever sequences they mix.
        present = [set(cache[0].tensors()) for cache in self.caches]
        common = set.intersection(*present) - {"camera_cut"}  # a sample sets its own cut flags
        return tuple(f.name for f in fields(FrameBatch) if f.name in common)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return self.sample(index, self.epoch)

    def sample(self, index: int, epoch: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} is out of range: split '{self.split}' has {len(self)} windows")
        rng = np.random.default_rng([self.seed, epoch, index])
        position, start = self.windows[index]
        cache = self.caches[position]
        first = cache[start]
        # Every draw is made whether or not augmentation is on, so a crop's position does not depend on it.
        top = int(rng.integers(0, first.height - self.crop_size + 1))
        left = int(rng.integers(0, first.width - self.crop_size + 1))
        flip_x, flip_y = bool(rng.random() < 0.5), bool(rng.random() < 0.5)
        brightness = math.exp(rng.uniform(math.log(BRIGHTNESS_RANGE[0]), math.log(BRIGHTNESS_RANGE[1])))
        rotation = random_rotation(rng)

        frames = [self._crop(cache[start + offset], top, left) for offset in range(self.frames)]
        sample = {name: torch.cat([frame[name] for frame in frames]) for name in self.buffers}
        sample["camera_cut"] = torch.zeros(self.frames, dtype=torch.bool)
        sample["camera_cut"][0] = True
        if self.augment:
            _flip(sample, flip_x, flip_y)
            for name in RADIANCE_BUFFERS:
                if name in sample:
                    sample[name] = sample[name] * brightness
            sample["normal"] = torch.einsum("ij,tjhw->tihw", rotation, sample["normal"])
        return sample

    def _crop(self, frame: FrameBatch, top: int, left: int) -> dict[str, torch.Tensor]:
        size, s = self.crop_size, self.scale
        cropped = {}
        for name in self.buffers:
            tensor = getattr(frame, name)
            if name in TARGET_BUFFERS:
                cropped[name] = tensor[:, :, s * top:s * (top + size), s * left:s * (left + size)]
            elif tensor.dim() == 4:
                cropped[name] = tensor[:, :, top:top + size, left:left + size]
            else:  # jitter: cropping by whole pixels leaves the sub-pixel offset as it is
                cropped[name] = tensor
        return cropped


def random_rotation(rng: np.random.Generator) -> torch.Tensor:
    """A 3 x 3 rotation drawn uniformly over all rotations (a normalised 4D Gaussian is a uniform unit quaternion).

    Why rotate normals: they are world-space, and which world axis is up is each renderer's own convention (our
    generator's scenes are y-up, Blender's z-up). Trained on one convention, the fused network read Blender's
    z-up floor as something it had not seen: it blurred and flickered on Blender frames, and did not with the
    same normals turned y-up. A rotation of the whole sample leaves every comparison between normals (edges,
    the disocclusion test) as it was.
    """
    w, x, y, z = (q := rng.standard_normal(4)) / np.linalg.norm(q)
    matrix = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
              [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
              [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return torch.tensor(matrix, dtype=torch.float32)


def _flip(sample: dict[str, torch.Tensor], flip_x: bool, flip_y: bool) -> None:
    """Mirror a sample in place: images, and the signs of the x (or y) motion and jitter components.

    Mirroring x maps continuous position x to W - x. A sample at pixel centre + jitter and its previous position
    p + motion both map through it, so the mirrored image's jitter and motion are the negated ones.

    Normals are left alone: they are world-space directions, and mirroring the image does not mirror the world
    along any fixed world axis (which axis the image's x is depends on the camera), so there is no consistent
    sign to flip. The networks use normals to compare neighbouring pixels, which a mirror leaves unchanged.
    """
    for flip, axis, component in ((flip_x, -1, 0), (flip_y, -2, 1)):
        if not flip:
            continue
        for name, tensor in sample.items():
            if tensor.dim() == 4:
                sample[name] = torch.flip(tensor, dims=(axis,))
        sample["motion"] = sample["motion"].clone()
        sample["motion"][:, component] *= -1
        sample["jitter"] = sample["jitter"].clone()
        sample["jitter"][:, component] *= -1


def collate_crops(samples: list[dict[str, torch.Tensor]]) -> list[FrameBatch]:
    """Stack samples into a batch: one ``FrameBatch`` (N samples) per time step, T in all."""
    if not samples:
        raise ValueError("cannot collate an empty list of samples")
    stacked = {name: torch.stack([sample[name] for sample in samples], dim=1) for name in samples[0]}
    frames = next(iter(stacked.values())).shape[0]
    return [FrameBatch(**{name: tensor[t] for name, tensor in stacked.items()}) for t in range(frames)]
