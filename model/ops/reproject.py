"""Geometry consistency test between a pixel and its reprojection into the previous frame.

Temporal accumulation (SVGF, BMFR, WSKPN's preprocessing) may only reuse history for pixels that saw the same
surface in the previous frame. After backward warping (``warp.backward_warp``) the previous frame's depth and
normal are compared with the current ones; a pixel fails ("disoccluded") when it has no surface, when its
reprojection leaves the image, or when depth or normal disagree.
"""

from __future__ import annotations

import torch

from model.ops.warp import Jitter, backward_warp

__all__ = ["disocclusion_mask", "reproject_history"]


def disocclusion_mask(
    depth: torch.Tensor,
    normal: torch.Tensor,
    prev_depth: torch.Tensor,
    prev_normal: torch.Tensor,
    motion: torch.Tensor,
    depth_rel_tol: float = 0.1,
    normal_cos_tol: float = 0.9,
    jitter: Jitter = None,
) -> torch.Tensor:
    """Return ``valid`` (N, 1, H, W) bool: True where this pixel's history can be trusted.

    depth, prev_depth (N, 1, H, W): linear distance from the camera, 0 where no surface.
    normal, prev_normal (N, 3, H, W): shading normals (renormalized here, so their length does not matter).
    motion (N, 2, H, W) and the optional ``jitter``: see ``model.ops.warp``.

    valid = inside the previous image
            and depth > 0
            and |depth - prev_depth_warped| <= depth_rel_tol * depth
            and cos(normal, prev_normal_warped) >= normal_cos_tol.

    The previous buffers are warped with "nearest" (the pixel whose footprint holds the sample), not bilinear:
    at a silhouette a bilinear depth is a blend of foreground and background that belongs to no surface (it
    could even match some third surface by chance), and a blended normal is not a real normal. Nearest compares
    against one real sample of the previous frame. Its cost is a half-pixel positional error, which the relative
    tolerance absorbs on smooth surfaces. A previous depth of 0 (no surface) always fails the depth test.

    Depth is distance from each frame's own camera, so under camera motion the same point's depth changes a
    little between frames; ``depth_rel_tol`` must leave room for that (10% suits smooth camera paths).
    """
    n, _, h, w = depth.shape
    for name, t, c in (
        ("depth", depth, 1),
        ("prev_depth", prev_depth, 1),
        ("normal", normal, 3),
        ("prev_normal", prev_normal, 3),
    ):
        if t.shape != (n, c, h, w):
            raise ValueError(f"{name} must have shape {(n, c, h, w)}, got {tuple(t.shape)}")

    # One gather for both buffers: depth and normal share the same sample positions.
    prev = torch.cat([prev_depth, prev_normal.to(prev_depth.dtype)], dim=1)
    warped, inside = backward_warp(prev, motion, mode="nearest", padding="border", jitter=jitter)
    pd, pn = warped[:, :1], warped[:, 1:]

    depth_ok = (depth - pd).abs() <= depth_rel_tol * depth
    # Normalize defensively: zero normals (no surface) give cos = 0 and fail, unnormalized ones still compare.
    # sqrt of the product of squared lengths: torch's norm over the channel dimension of an NCHW tensor takes a
    # slow strided path on the CPU, which every temporal method would pay every frame.
    lengths = ((normal * normal).sum(dim=1, keepdim=True) * (pn * pn).sum(dim=1, keepdim=True)).sqrt()
    cos = (normal * pn).sum(dim=1, keepdim=True) / lengths.clamp_min(1e-12)
    normal_ok = cos >= normal_cos_tol
    return inside & (depth > 0) & (pd > 0) & depth_ok & normal_ok


def reproject_history(
    history: torch.Tensor,
    count: torch.Tensor,
    depth: torch.Tensor,
    normal: torch.Tensor,
    prev_depth: torch.Tensor,
    prev_normal: torch.Tensor,
    motion: torch.Tensor,
    jitter: torch.Tensor,
    prev_jitter: torch.Tensor,
    depth_rel_tol: float = 0.1,
    normal_cos_tol: float = 0.9,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bring a pixel-centred history into this frame: (warped history, warped count, valid mask).

    Two kinds of previous buffers live at two kinds of positions, so they are read at different places:

    - ``history`` and ``count`` are what a method accumulated *per pixel*: blends of samples from many jitter
      offsets, i.e. values at pixel centres. This pixel's centre shows what the previous frame showed at
      centre + motion (motion varies smoothly over the pixel), so they are read there, without jitter. Reading
      at centre + jitter + motion would shift the whole history by this frame's jitter every frame.
    - ``prev_depth`` / ``prev_normal`` are the previous frame's *samples*, taken at its pixel centres + its
      jitter. This frame's sample (centre + jitter) was at centre + jitter + motion in the previous image,
      which is centre + (jitter - prev_jitter) + motion in the previous buffer's pixel grid.

    The history is warped bilinearly (a sub-pixel motion must not snap it to the grid), the count with
    "nearest" so that it stays the count of one real previous pixel. ``jitter`` and ``prev_jitter`` are (N, 2).
    """
    warped, _ = backward_warp(history, motion, mode="bilinear")
    warped_count, _ = backward_warp(count, motion, mode="nearest")
    valid = disocclusion_mask(depth, normal, prev_depth, prev_normal, motion, depth_rel_tol=depth_rel_tol,
                              normal_cos_tol=normal_cos_tol, jitter=jitter - prev_jitter)
    # A camera cut zeroes a sample's state (methods.base.drop_history): count 0 means no history.
    return warped, warped_count, valid & (warped_count > 0)
