"""Backward warping with motion vectors, and the motion-vector preparation it needs.

Conventions (fixed for the whole project; docs/frame-format.md, "Conventions"):

- image coordinates are continuous, origin at the top-left corner of pixel (0, 0), x right, y down;
  pixel (x, y) covers [x, x+1) x [y, y+1) and its centre is (x + 0.5, y + 0.5);
- motion is an (N, 2, H, W) tensor in pixels, channel 0 = x, channel 1 = y; motion(p) is the position of p's
  surface point in the previous frame minus its position in this frame, so the previous frame is read at
  ``centre(p) + motion(p)`` ("backward warping": every output pixel gathers, nothing is scattered).

Jitter: the frame format measures motion from this frame's jittered sample position ``centre + jitter`` (and lands
on the previous frame's unjittered projection), so the exact read position is ``centre + jitter + motion``. Every
function taking ``jitter`` adds it (default none, i.e. ``centre + motion``); pass the frame's ``jitter`` header
when reading an unjittered history, or leave it out where half a pixel does not matter.

``grid_sample(align_corners=False)`` puts normalized -1 on the left edge of pixel 0 and +1 on the right edge of
pixel W-1, which is exactly our continuous coordinate scaled by 2/W, so the conversion is ``g = 2 * x / W - 1``
and a sample at a pixel centre returns that pixel unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from model.ops.graph_breaks import outside_compiled_graph

__all__ = ["Jitter", "backward_warp", "bilinear_spread", "sample_positions", "upscale_motion", "dilate_motion_by_depth"]

_MODES = ("bilinear", "bicubic", "nearest")
_PADDINGS = ("border", "zeros")


def _check_motion(image: torch.Tensor, motion: torch.Tensor) -> None:
    if image.dim() != 4:
        raise ValueError(f"expected an (N, C, H, W) image, got shape {tuple(image.shape)}")
    n, _, h, w = image.shape
    if motion.shape != (n, 2, h, w):
        raise ValueError(f"motion must have shape {(n, 2, h, w)} to match the image, got {tuple(motion.shape)}")


Jitter = Sequence[float] | torch.Tensor | None


def sample_positions(motion: torch.Tensor, jitter: Jitter = None) -> torch.Tensor:
    """Continuous positions ``centre(p) + jitter + motion(p)`` (N, 2, H, W), channel 0 = x, 1 = y, in pixels.

    jitter: None, one (x, y) pair for the whole batch, or an (N, 2) tensor (one per sample).
    """
    n, _, h, w = motion.shape
    xs = torch.arange(w, device=motion.device, dtype=motion.dtype) + 0.5
    ys = torch.arange(h, device=motion.device, dtype=motion.dtype) + 0.5
    centre = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=0)  # (2, H, W), [0] = x, [1] = y
    pos = centre.unsqueeze(0) + motion
    if jitter is not None:
        j = torch.as_tensor(jitter, dtype=motion.dtype, device=motion.device)
        if j.shape not in ((2,), (n, 2)):
            raise ValueError(f"jitter must be an (x, y) pair or an ({n}, 2) tensor, got shape {tuple(j.shape)}")
        pos = pos + j.reshape(-1, 2, 1, 1)
    return pos


def backward_warp(
    prev: torch.Tensor,
    motion: torch.Tensor,
    mode: str = "bilinear",
    padding: str = "border",
    jitter: Jitter = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read ``prev`` (N, C, H, W) at ``centre(p) + motion(p)`` (+ ``jitter``) for every pixel p of this frame.

    mode:
      - "bilinear": ``grid_sample`` bilinear; differentiable in ``prev`` and ``motion``.
      - "bicubic": ``grid_sample`` bicubic, torch's cubic convolution with A = -0.75 on the 4x4 taps around the
        sample. Sharper than bilinear (JNDS warps history this way to avoid blur accumulating over frames) but it
        overshoots at edges, so non-negative inputs can come back slightly negative: clamp if that matters.
      - "nearest": the pixel whose footprint [x, x+1) x [y, y+1) contains the sample, i.e. ``floor`` of the
        position. Implemented with ``gather`` rather than ``grid_sample(mode="nearest")`` because the latter rounds
        half to even and would disagree with the pixel-footprint convention on exact half-pixel motions.
        Returns real (unblended) values, which is what geometry buffers need; no gradient w.r.t. motion.
    padding:
      - "border": taps outside the image take the value of the nearest edge pixel;
      - "zeros": taps outside the image are 0 (so bilinear samples within half a pixel of the edge fade to 0).

    Returns ``(warped, inside)``: ``warped`` (N, C, H, W) and ``inside`` (N, 1, H, W) bool, True where the sample
    position lies inside the previous image, 0 <= x < W and 0 <= y < H. Pixels with ``inside`` False have no
    history whatever the padding; the padding only decides what value they carry.
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if padding not in _PADDINGS:
        raise ValueError(f"padding must be one of {_PADDINGS}, got {padding!r}")
    _check_motion(prev, motion)
    motion = motion.to(prev.dtype)
    n, c, h, w = prev.shape
    pos = sample_positions(motion, jitter)
    px, py = pos[:, 0], pos[:, 1]
    inside = ((px >= 0) & (px < w) & (py >= 0) & (py < h)).unsqueeze(1)

    if mode == "nearest":
        ix = torch.floor(px).long()
        iy = torch.floor(py).long()
        flat = (iy.clamp(0, h - 1) * w + ix.clamp(0, w - 1)).view(n, 1, h * w).expand(n, c, h * w)
        warped = torch.gather(prev.reshape(n, c, h * w), 2, flat).view(n, c, h, w)
        if padding == "zeros":
            warped = torch.where(inside, warped, torch.zeros((), dtype=warped.dtype, device=warped.device))
        return warped, inside

    # Normalize with the image size (not size - 1): that is what align_corners=False means. Written as
    # (2x - W) / W, one rounding, rather than x * (2/W) - 1, three: keeps integer motions within ~1e-7 px in
    # float32 on small images (torch's own unnormalization then limits large ones to float32's ~1e-4 px at 2k).
    size = torch.tensor([w, h], dtype=prev.dtype, device=prev.device)
    grid = ((2.0 * pos.permute(0, 2, 3, 1) - size) / size).contiguous()  # (N, H, W, 2) with [..., 0] = x
    return _grid_sample(prev, grid, mode, padding), inside


def _grid_sample(image: torch.Tensor, grid: torch.Tensor, mode: str, padding: str) -> torch.Tensor:
    if mode == "bicubic":
        # inductor's decomposition of the bicubic read is slower on the CPU than torch's kernel: kept out of a graph
        return _eager_grid_sample(image, grid, mode, padding)
    return _split_grid_sample(image, grid, mode, padding)


def _split_grid_sample(image: torch.Tensor, grid: torch.Tensor, mode: str, padding: str) -> torch.Tensor:
    """``F.grid_sample(..., align_corners=False)``, with one image's output rows split over torch's threads. On the
    CPU grid_sample runs its batch items in parallel and each on one thread, so a single frame (every session's
    step) used one core of two; split into items of part of the rows each, reading the same image, it uses them
    all. Each pixel's arithmetic is the same, so the outputs are the same to the bit. Batches, other devices and
    exports (a graph with the machine's thread count in it) read as one call."""
    n, channels = image.shape[:2]
    rows, columns = grid.shape[1:3]
    # compiling first: under torch.compile the thread count is no tensor, and reading it would break the graph
    if torch.compiler.is_compiling() or n != 1 or image.device.type != "cpu" or torch.jit.is_tracing():
        return F.grid_sample(image, grid, mode=mode, padding_mode=padding, align_corners=False)
    parts = min(torch.get_num_threads(), rows)
    if parts < 2:
        return F.grid_sample(image, grid, mode=mode, padding_mode=padding, align_corners=False)
    extra = -rows % parts  # rows repeated so every part is as tall, then cropped
    if extra:
        grid = torch.cat([grid, grid[:, -1:].expand(1, extra, columns, 2)], dim=1)
    stacked = grid.reshape(parts, (rows + extra) // parts, columns, 2)
    warped = F.grid_sample(image.expand(parts, *image.shape[1:]), stacked, mode=mode, padding_mode=padding,
                           align_corners=False)
    return warped.transpose(0, 1).reshape(1, channels, rows + extra, columns)[:, :, :rows]


def bilinear_spread(motion: torch.Tensor) -> torch.Tensor:
    """How much a bilinear read at ``centre + motion`` blurs, per pixel (N, 1, H, W), in [0, 1]: the variance of
    its taps' positions, f (1 - f) on each axis for the fractional part f of the motion, summed and doubled. 0 at a
    whole-pixel motion (the read is one pixel), 1 at half a pixel on both axes (four pixels, a quarter each).
    A buffer read this way every frame and kept blurs by this much more each frame."""
    if motion.dim() != 4 or motion.shape[1] != 2:
        raise ValueError(f"motion must be (N, 2, H, W), got shape {tuple(motion.shape)}")
    f = motion - torch.floor(motion)
    return 2 * (f * (1 - f)).sum(dim=1, keepdim=True)


def upscale_motion(motion: torch.Tensor, scale: float, mode: str = "nearest") -> torch.Tensor:
    """Resize a motion field (N, 2, H, W) by ``scale`` and express it in the new resolution's pixels.

    Motion is measured in pixels, so the values are multiplied as well as resized: channel 0 by W_out / W and
    channel 1 by H_out / H (both equal ``scale`` whenever ``scale * size`` is an integer). Output size is
    ``round(scale * H) x round(scale * W)``.

    mode "nearest" ("nearest-exact" in torch terms, the align_corners=False choice: each output pixel takes the
    input pixel under its centre) keeps object boundaries hard, so a foreground pixel never gets half of a
    background motion; "bilinear" (align_corners=False) is smoother inside objects but mixes motions at edges.
    """
    if motion.dim() != 4 or motion.shape[1] != 2:
        raise ValueError(f"motion must be (N, 2, H, W), got {tuple(motion.shape)}")
    if scale <= 0:
        raise ValueError(f"scale must be positive, got {scale}")
    _, _, h, w = motion.shape
    out_h, out_w = int(round(h * scale)), int(round(w * scale))
    if mode == "nearest":
        resized = F.interpolate(motion, size=(out_h, out_w), mode="nearest-exact")
    elif mode == "bilinear":
        resized = F.interpolate(motion, size=(out_h, out_w), mode="bilinear", align_corners=False)
    else:
        raise ValueError(f"mode must be 'nearest' or 'bilinear', got {mode!r}")
    factor = torch.tensor([out_w / w, out_h / h], dtype=motion.dtype, device=motion.device).view(1, 2, 1, 1)
    return resized * factor


def dilate_motion_by_depth(motion: torch.Tensor, depth: torch.Tensor, k: int = 3) -> torch.Tensor:
    """For each pixel, take the motion of the closest surface (smallest positive depth) in its k x k window.

    Why: at a silhouette a background pixel next to a moving foreground object is usually covered by that object
    in the previous frame (or its history is smeared by it); using the foreground's motion there is the standard
    TAA/upscaler fix that keeps edges of moving objects from ghosting. ``depth == 0`` means "no surface" and is
    never chosen; pixels outside the image are ignored. When no pixel of the window has a surface the pixel keeps
    its own motion. Ties go to the centre pixel first, then to the first offset in row-major order.

    motion (N, 2, H, W), depth (N, 1, H, W), k odd. Gradients flow to the selected motion values.
    """
    if k < 1 or k % 2 == 0:
        raise ValueError(f"k must be a positive odd integer, got {k}")
    _check_motion(depth, motion)
    if depth.shape[1] != 1:
        raise ValueError(f"depth must be (N, 1, H, W), got {tuple(depth.shape)}")
    h, w = depth.shape[-2:]
    r = k // 2
    inf = torch.tensor(float("inf"), dtype=depth.dtype, device=depth.device)
    key = torch.where(depth > 0, depth, inf)
    # Out-of-image taps get depth +inf so they never win; their motion value is irrelevant (zeros).
    key_pad = F.pad(key, (r, r, r, r), value=float("inf"))
    mot_pad = F.pad(motion, (r, r, r, r))
    best = key
    out = motion
    # A loop over k*k shifted views keeps memory at one image instead of k*k unfolded copies.
    for dy in range(k):
        for dx in range(k):
            if dy == r and dx == r:
                continue
            cand = key_pad[..., dy : dy + h, dx : dx + w]
            better = cand < best
            best = torch.where(better, cand, best)
            out = torch.where(better, mot_pad[..., dy : dy + h, dx : dx + w], out)
    return out


_eager_grid_sample = outside_compiled_graph(_split_grid_sample)
