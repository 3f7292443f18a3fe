"""The ghosting measure on tiny synthetic sequences whose trails and errors are known in closed form."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from model.evaluation.ghosting import CHANGE_THRESHOLD, TRAIL_FRAMES, changed_regions, ghosting_error, trail_masks
from model.evaluation.metrics import PSNR_CAP_DB

H, W = 16, 32
BACKGROUND = 0.0
SQUARE = 1.0  # displayed 1.0 over a displayed 0.0: one square pixel moves a 3x3 mean by 1/9 > CHANGE_THRESHOLD


def box(top: int, left: int, size: int, height: int = H, width: int = W) -> torch.Tensor:
    mask = torch.zeros(height, width, dtype=torch.bool)
    mask[top:top + size, left:left + size] = True
    return mask


def dilate(mask: torch.Tensor) -> torch.Tensor:
    """The 3x3 dilation of a (H, W) mask: every pixel whose 3x3 window holds a True pixel."""
    return F.max_pool2d(mask[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0


def frames_of(squares: list[torch.Tensor | None]) -> torch.Tensor:
    """(T, 3, H, W) references: the background with each frame's square (None: no square) set to SQUARE."""
    frames = torch.full((len(squares), 3, H, W), BACKGROUND)
    for t, square in enumerate(squares):
        if square is not None:
            frames[t, :, square] = SQUARE
    return frames


def still(frames: int, height: int = H, width: int = W) -> torch.Tensor:
    return torch.zeros(frames, 2, height, width)


def sliding_squares(frames: int, step: int = 5) -> list[torch.Tensor]:
    """A 5x5 square moving right by ``step`` pixels a frame (static camera), from x = 1."""
    return [box(5, 1 + step * t, 5) for t in range(frames)]


# ------------------------------------------------------------------------------------------ changed regions

def test_a_static_scene_has_no_change_no_trail_and_no_ghosting_score():
    texture = torch.rand(3, H, W, generator=torch.Generator().manual_seed(0))
    references = texture.expand(6, 3, H, W).contiguous()
    assert not changed_regions(references, still(6)).any()
    trails = trail_masks(references, still(6))
    assert trails.shape == (6, 1, H, W) and not trails.any()
    assert ghosting_error(references * 0.5, references, trails) is None


def test_camera_motion_alone_is_no_change_even_over_sub_pixel_detail():
    generator = torch.Generator().manual_seed(1)
    # Integer pan: content moves 2 px left a frame, so frame t-1 held pixel x's content at x + 2 (motion +2).
    wide = torch.rand(3, H, W + 20, generator=generator)
    references = torch.stack([wide[:, :, 2 * t:2 * t + W] for t in range(6)])
    motion = still(6)
    motion[:, 0] = 2.0
    changed = changed_regions(references, motion)
    # Only the last columns, whose content entered from outside the image (border-clamped prediction), change.
    assert not changed[..., :W - 3].any() and changed[1:, ..., W - 1].any()
    # Quarter-pixel pan of detail finer than a pixel (box-filtered like a reference): resampling is no change.
    fine = torch.rand(3, 4 * H, 4 * W + 40, generator=generator)
    references = torch.stack([F.avg_pool2d(fine[None, :, :, t:t + 4 * W], 4)[0] for t in range(6)])
    motion = still(6)
    motion[:, 0] = 0.25
    assert not changed_regions(references, motion)[..., 1:-1, 1:-2].any()


def test_a_square_that_vanishes_or_appears_changes_exactly_its_3x3_dilation():
    square = box(4, 10, 4)
    references = frames_of([square, None, square])
    changed = changed_regions(references, still(3))
    assert not changed[0].any()
    assert torch.equal(changed[1, 0], dilate(square)) and torch.equal(changed[2, 0], dilate(square))
    # A change under the threshold is none: a square displayed half the threshold brighter than the background.
    faint = frames_of([None, None])
    faint[1, :, square] = (CHANGE_THRESHOLD / 2) ** 2.2
    assert not changed_regions(faint, still(2)).any()


# ---------------------------------------------------------------------------------------------------- trails

@pytest.mark.parametrize("scale", [1, 2])
def test_the_trail_lasts_trail_frames_and_follows_the_camera(scale):
    # A flat background (a pan changes nothing) panning 2 reference pixels left a frame; a square blinks on at
    # frame 1 only. Frame 1 changed where it appeared, frame 2 where it vanished (2 px further left on screen).
    square = box(6, 20, 4)
    references = frames_of([None, square] + [None] * 6)
    motion = torch.full((8, 2, H // scale, W // scale), 2.0 / scale)  # render resolution: upscaled x scale
    motion[:, 1] = 0.0
    changed = changed_regions(references, motion)
    appeared, vanished = dilate(square), dilate(square).roll(-2, dims=1)
    assert torch.equal(changed[1, 0], appeared) and torch.equal(changed[2, 0], vanished)
    assert not changed[3:].any()
    trails = trail_masks(references, motion)
    assert TRAIL_FRAMES == 4 and not trails[0].any()
    for t in range(1, 8):
        expected = torch.zeros(H, W, dtype=torch.bool)
        if t - 1 < TRAIL_FRAMES:
            expected |= appeared.roll(-2 * (t - 1), dims=1)
        if 2 <= t and t - 2 < TRAIL_FRAMES:
            expected |= vanished.roll(-2 * (t - 2), dims=1)
        assert torch.equal(trails[t, 0], expected), t
    assert trails[5].any() and not trails[6].any()  # the vanishing was at frame 2: in the trail for frames 2-5
    assert torch.equal(trail_masks(references, motion, frames=1), changed)


def test_a_camera_cut_drops_the_trail():
    references = frames_of(sliding_squares(5))
    changed = changed_regions(references, still(5), [False, False, True, False, False])
    trails = trail_masks(references, still(5), [False, False, True, False, False])
    assert changed[1].any() and not changed[2].any() and not trails[2].any()
    assert torch.equal(trails[3], changed[3]) and torch.equal(trails[4], changed[3] | changed[4])


def test_the_trail_covers_where_a_moving_square_was_in_the_last_frames():
    squares = sliding_squares(6)
    trails = trail_masks(frames_of(squares), still(6))
    for t in range(1, 6):
        for k in range(1, min(t, TRAIL_FRAMES) + 1):
            assert bool(trails[t, 0][squares[t - k]].all()), (t, k)


def test_bad_shapes_are_refused_with_what_is_wrong():
    references = frames_of([None, None])
    with pytest.raises(ValueError, match="motions must be"):
        changed_regions(references, still(3))
    with pytest.raises(ValueError, match="times one integer scale"):
        changed_regions(references, torch.zeros(2, 2, H, W // 3))
    with pytest.raises(ValueError, match="camera_cuts has 1 entries for 2 frames"):
        trail_masks(references, still(2), [False])
    with pytest.raises(ValueError, match="at least one frame"):
        trail_masks(references, still(2), frames=0)
    with pytest.raises(ValueError, match="bool mask"):
        ghosting_error(references, references, torch.ones(2, 1, H, W))


# ---------------------------------------------------------------------------------------------- the measure

def test_an_output_that_keeps_the_old_square_scores_worse_than_one_that_does_not():
    squares = sliding_squares(6)
    references = frames_of(squares)
    trails = trail_masks(references, still(6))
    perfect = ghosting_error(references, references, trails)
    assert perfect["error"] == 0.0 and perfect["psnr"] == pytest.approx(PSNR_CAP_DB)
    assert perfect["frames"] == 5 and perfect["per_frame_error"][0] is None

    # Keeps the previous frame's square at full brightness (a method trusting its history).
    ghosted = torch.stack([references[0]] + [torch.maximum(references[t], references[t - 1]) for t in range(1, 6)])
    ghost = ghosting_error(ghosted, references, trails)
    contrast = 1.0  # displayed square minus displayed background
    for t in range(1, 6):
        trail = trails[t, 0]
        ghost_pixels = int((squares[t - 1] & ~squares[t] & trail).sum())
        assert ghost_pixels == 25  # the whole old square lies in the trail
        assert ghost["per_frame_error"][t] == pytest.approx(ghost_pixels * contrast / int(trail.sum()), rel=1e-5)
    expected_psnr = [10 * math.log10(int(trails[t].sum()) / (25 * contrast ** 2)) for t in range(1, 6)]
    assert ghost["psnr"] == pytest.approx(sum(expected_psnr) / 5, rel=1e-5)

    # Noisy but without a ghost: a small error everywhere, far below the ghost's.
    generator = torch.Generator().manual_seed(2)
    noisy = (references + 0.001 * torch.randn(references.shape, generator=generator)).clamp_min(0)
    clean_enough = ghosting_error(noisy, references, trails)
    assert 0 < clean_enough["error"] < ghost["error"] / 4 and clean_enough["psnr"] > ghost["psnr"] + 6
