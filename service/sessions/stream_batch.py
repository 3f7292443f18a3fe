"""A session stream's frame message (client.codec.StreamFrame) straight to the FrameBatch a step takes.

The reference reading of a stream frame is model.layouts.read_bundle_buffers (what a POSTed EXR of the ``denoiser``
layout goes through in a live session) followed by FrameBatch.from_bundles: NumPy, and shaped for EXR files, so
the message's planar arrays are turned to (H, W, C) float32 and back to (C, H, W), a round trip whose cost is a
good part of the fastest model's step at small sizes. ``stream_frame_batch`` builds the same
batch from the planes in torch: the float16 -> float32 cast, the ``denoiser`` layout's one conversion (no normal
where nothing is hit) and, as the clean-frame test, the two checks a sanitizable frame is still held to (unit-length
normals where depth > 0; diffuse + specular == color). A frame that is not clearly clean by them (a normal to
renormalise or refuse, a lobe split off by more than the tolerance, or within a rounding of either bound) goes the
reference way, which repairs, reports or refuses it exactly as the POST route does; so the batch, the repairs and
the errors are the reference's in every case, and the fast way only ever answers frames it has proved clean.
The fast way also takes one minimum and maximum per channel of the whole message, which is all the input check
(model.io.sanitize) needs to pass a clean frame, so a session step need not look at the frame a second time.

Run it on a thread whose torch thread count is set (service.sessions.torch_thread; sessions use threads of one torch thread,
SessionStore.read_frame), not on a request thread, which would grow an OpenMP team of its own.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np
import torch

from model.io.frames import LOBE_SPLIT_TOLERANCE, NORMAL_LENGTH_TOLERANCE
from model.layouts.read import read_bundle_buffers
from model.methods.base import FrameBatch
from model.io.sanitize import bounds_need_no_repair
from client.codec import StreamFrame

# Test bounds drawn this much inside the reference's, so float rounding (torch's sums against NumPy's) can never
# call a frame clean that the reference would repair or refuse; a frame this close to a bound goes the slow way.
_MARGIN = 1e-5


class StreamRead(NamedTuple):
    """A frame message read: its batch, the repairs made reading it, and whether the input check
    (model.io.sanitize) is already known to find nothing to repair in the batch (False: the step must run it)."""

    batch: FrameBatch
    repairs: tuple[str, ...]
    plainly_valid: bool = False


def stream_frame_batch(message: StreamFrame, device: torch.device | str = "cpu",
                       source: str = "<frame message>") -> StreamRead:
    """The frame of a message from ``decode_frame`` as a batch of one on ``device`` and the repairs made reading
    it (lossy normals renormalised), exactly as ``read_bundle_buffers`` + ``FrameBatch.from_bundles`` give them;
    FrameError naming ``source`` for a frame they refuse. A frame read the fast way also says whether it is
    plainly valid for the input check, from one minimum and maximum per channel of the whole message."""
    with warnings.catch_warnings():  # a read-only view is fine: it is only read, into a tensor of its own
        warnings.simplefilter("ignore", UserWarning)
        view = torch.from_numpy(message.planes)
    # One cast for every buffer (they lie one after another in the message), then a view per buffer.
    planes = view.to(device=device, dtype=torch.float32, copy=True).unsqueeze(0)
    buffers, channels, first = {}, {}, 0
    for name, array in message.buffers.items():
        count = 1 if array.ndim == 2 else array.shape[0]
        buffers[name], channels[name] = planes[:, first:first + count], (first, first + count)
        first += count
    hit = buffers["depth"] > 0
    if not _clearly_clean(buffers, hit):
        return StreamRead(*_reference_batch(message, device, source))
    # Bounds of the message's values (normals where nothing was hit included: a NaN there only costs the
    # pixel-wise check). After the test above, every normal left is unit length or zero, as the check wants.
    # Every channel's own bound must be finite first: Python's min and max over a list can step past a NaN.
    lows, highs = planes.amin(dim=(0, 2, 3)).tolist(), planes.amax(dim=(0, 2, 3)).tolist()
    plainly_valid = all(map(math.isfinite, lows + highs)) and bounds_need_no_repair(
        {name: (min(lows[a:b]), max(highs[a:b])) for name, (a, b) in channels.items()}, message.jitter)
    buffers["normal"] = torch.where(hit, buffers["normal"], torch.zeros((), device=hit.device))
    jitter = torch.tensor([message.jitter], dtype=torch.float32, device=device)
    camera_cut = torch.tensor([message.camera_cut], dtype=torch.bool, device=device)
    return StreamRead(FrameBatch(jitter=jitter, camera_cut=camera_cut, **buffers), (), plainly_valid)


def _clearly_clean(buffers: dict[str, torch.Tensor], hit: torch.Tensor) -> bool:
    """Whether the reference reading would neither repair nor refuse the frame: every normal where something was
    hit (``hit``: depth > 0) is unit length within the tolerance, and diffuse and specular come together and add
    up to color. Normals with a NaN or Inf are the sanitizer's either way; here they only send the frame the
    reference way. Reductions to one maximum each (NaN taken as no excess), not masks: this runs every frame."""
    tolerance = NORMAL_LENGTH_TOLERANCE - _MARGIN
    # |n| within 1 +- t  <=>  |n|^2 within (1 +- t)^2  <=>  | |n|^2 - (1 + t^2) | <= 2t
    off = buffers["normal"].square().sum(dim=1, keepdim=True).sub_(1 + tolerance * tolerance).abs_()
    if float(torch.where(hit, off, 0.0).nan_to_num_(nan=0.0).amax()) > 2 * tolerance:
        return False
    diffuse, specular = buffers.get("diffuse"), buffers.get("specular")
    if diffuse is None and specular is None:
        return True
    if diffuse is None or specular is None:
        return False  # the reference names the missing one
    color = buffers["color"]
    # |diffuse + specular - color| - k (1 + color) > 0, where finite  <=>  the finite |...| - k color > k
    k = LOBE_SPLIT_TOLERANCE - _MARGIN
    excess = (diffuse + specular).sub_(color).abs_().sub_(color, alpha=k)
    return not float(excess.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0).amax()) > k


def _reference_batch(message: StreamFrame, device: torch.device | str,
                     source: str) -> tuple[FrameBatch, tuple[str, ...]]:
    read = read_bundle_buffers({name: message.hwc(name) for name in message.buffers}, jitter=message.jitter,
                               frame_index=message.frame_index or 0, camera_cut=message.camera_cut, source=source)
    return FrameBatch.from_bundles([read.frame], scale=None, device=device), read.repairs
