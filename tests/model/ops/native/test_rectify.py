"""The native 1x rectification equals the torch moments, box and clips it replaces, on seeded frames."""

import pytest
import torch

from model.ops import native
from model.ops.native.rectify import clip_pair_x1
from model.ops.rectify import clip_to_bounds, moment_bounds, neighbourhood_moments

SIZES = [(37, 53), (1, 1), (2, 3), (5, 4)]


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():
        yield


def _expected(guide, first, second):
    box = moment_bounds(*neighbourhood_moments(guide))
    return clip_to_bounds(first, *box), None if second is None else clip_to_bounds(second, *box)


def _frames(seed: int, h: int, w: int):
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(1, 3, h, w, generator=g) for _ in range(3)]


@pytest.mark.parametrize("size", SIZES)
def test_equals_the_torch_clips(size):
    guide, first, second = _frames(sum(size), *size)
    first_out, second_out = clip_pair_x1(guide, first, second)
    expected_first, expected_second = _expected(guide, first, second)
    torch.testing.assert_close(first_out, expected_first, atol=1e-5, rtol=0)
    torch.testing.assert_close(second_out, expected_second, atol=1e-5, rtol=0)
    assert not torch.equal(first_out, first)  # the box clips something


def test_one_image():
    guide, first, _ = _frames(1, 37, 53)
    first_out, second_out = clip_pair_x1(guide, first, None)
    assert second_out is None
    torch.testing.assert_close(first_out, _expected(guide, first, None)[0], atol=1e-5, rtol=0)


def test_a_flat_guide_clips_to_its_colour():
    """No spread: the variance rounds to about 0 (negative ones are clamped), the box closes on the guide's colour."""
    guide = torch.tensor([0.3, 0.6, 0.2]).view(1, 3, 1, 1).expand(1, 3, 9, 11).contiguous()
    _, first, second = _frames(2, 9, 11)
    first_out, second_out = clip_pair_x1(guide, first, second)
    expected_first, expected_second = _expected(guide, first, second)
    torch.testing.assert_close(first_out, expected_first, atol=1e-5, rtol=0)
    torch.testing.assert_close(second_out, expected_second, atol=1e-5, rtol=0)
    torch.testing.assert_close(first_out, guide, atol=1e-3, rtol=0)


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_split_the_rows_without_changing_them(threads):
    guide, first, second = _frames(3, 37, 53)
    single = clip_pair_x1(guide, first, second)
    torch.set_num_threads(threads)
    parallel = clip_pair_x1(guide, first, second)
    assert torch.equal(parallel[0], single[0]) and torch.equal(parallel[1], single[1])


def test_not_usable_where_the_torch_ops_must_run():
    guide, first, second = _frames(4, 4, 4)
    assert native.usable("rectify", guide, first, second)
    assert not native.usable("rectify", guide.double(), first, second)
    native.set_enabled(False)
    try:
        assert not native.usable("rectify", guide, first, second)
    finally:
        native.set_enabled(True)
