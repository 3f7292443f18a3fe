"""model.io.synthetic: made-up frames are valid, reproducible from a seed and different across phases."""

from __future__ import annotations

import numpy as np

from model.io.frames import validate_frame
from model.io.synthetic import moving_pattern_frames


def test_every_frame_is_valid_and_numbered_in_order():
    frames = moving_pattern_frames(3, 12, np.random.default_rng(0), references=True)
    for index, frame in enumerate(frames):
        validate_frame(frame, f"frame {index}")
        assert frame.frame_index == index
        assert frame.color.shape == (12, 12, 3) and frame.references[1].shape == (12, 12, 3)
    assert not moving_pattern_frames(1, 12, np.random.default_rng(0))[0].references


def test_the_same_seed_gives_the_same_frames_and_other_phases_other_ones():
    first, again = (moving_pattern_frames(2, 8, np.random.default_rng(4)) for _ in range(2))
    shifted = moving_pattern_frames(2, 8, np.random.default_rng(4), phases=(1, 3, 5))
    for a, b, c in zip(first, again, shifted):
        np.testing.assert_array_equal(a.color, b.color)
        assert a.jitter == b.jitter
        assert not np.array_equal(a.color, c.color)


def test_frames_can_be_wider_than_tall():
    frame = moving_pattern_frames(1, (12, 5), np.random.default_rng(0))[0]
    assert (frame.width, frame.height) == (12, 5) and frame.depth.shape == (5, 12)
