"""Image operations shared by every method: warping, accumulation, kernel application, pyramids, tone maps.

Pure PyTorch on batched (N, C, H, W) float tensors, device-agnostic, differentiable where it makes sense.
One concern per module:

- ``warp``: backward warping with motion vectors, motion upscaling and depth-guided dilation;
- ``reproject``: the depth/normal disocclusion test;
- ``accumulate``: exponential temporal accumulation with sample counts, luminance moments;
- ``kernels``: per-pixel k x k kernel application (KPCN/AFN);
- ``splat``: WSKPN weight-sharing kernels as box filters, and kernel-size fusion;
- ``pyramid``: 2x down/upsampling and pyramids;
- ``tonemap``: mu-law, log, display encoding (forward/inverse pairs) and luminance;
- ``rectify``: history rectification (neighbourhood clamp, variance clip);
- ``stale_history``: a test of a reprojected history against the 1 spp frame's unbiased samples;
- ``graph_breaks``: calls that stay out of a ``torch.compile`` graph compiled around them.

Coordinate and motion conventions are spelled out in ``warp``'s docstring (and docs/frame-format.md).
"""

from model.ops.accumulate import accumulate, accumulate_moments, update_count
from model.ops.kernels import apply_pixel_kernels, kernel_offsets
from model.ops.pyramid import build_pyramid, downsample2x, upsample2x
from model.ops.reproject import disocclusion_mask
from model.ops.splat import WSKPN_SIZES, box_sum, fuse_kernel_sizes, weight_sharing_filter, weight_sharing_fused
from model.ops.tonemap import (
    display_decode,
    display_encode,
    log_tonemap,
    log_tonemap_inverse,
    luminance,
    mulaw,
    mulaw_inverse,
)
from model.ops.warp import backward_warp, dilate_motion_by_depth, sample_positions, upscale_motion

__all__ = [
    "accumulate",
    "accumulate_moments",
    "update_count",
    "apply_pixel_kernels",
    "kernel_offsets",
    "build_pyramid",
    "downsample2x",
    "upsample2x",
    "disocclusion_mask",
    "WSKPN_SIZES",
    "box_sum",
    "fuse_kernel_sizes",
    "weight_sharing_filter",
    "weight_sharing_fused",
    "display_decode",
    "display_encode",
    "log_tonemap",
    "log_tonemap_inverse",
    "luminance",
    "mulaw",
    "mulaw_inverse",
    "backward_warp",
    "dilate_motion_by_depth",
    "sample_positions",
    "upscale_motion",
]
