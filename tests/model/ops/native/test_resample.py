"""The native 1x resample equals the fused step's torch resample (``sample_mean_resample``, ``unjittered_resample``)
on seeded frames, at the jitters the frame format produces."""

import contextlib

import pytest
import torch

from model.methods.fused import sample_mean_resample, unjittered_resample
from model.ops import native
from model.ops.native.resample import sample_mean_resample_x1, unjittered_resample_x1

# whole, half and quarter pixels (Halton jitters land on quarters; at +-0.5 the nearest read is half-way between two
# pixels and rounds half to even), eighths and an irregular shift
JITTERS = [(0.0, 0.0), (0.25, -0.25), (-0.5, 0.5), (0.5, 0.0), (0.0, -0.5), (0.125, 0.375), (-0.375, 0.75 - 1),
           (0.3, -0.1)]
SIZES = [(37, 53), (1, 1), (2, 3), (5, 4)]


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():
        yield


@contextlib.contextmanager
def _torch_ops():
    """The torch reference, whether or not the fused step hands these reads to the native kernels."""
    native.set_enabled(False)
    try:
        yield
    finally:
        native.set_enabled(True)


def _case(seed: int, h: int, w: int):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, 3, h, w, generator=g)
    count = torch.randint(0, 9, (1, 1, h, w), generator=g).float()
    count.view(-1)[:3] = torch.tensor([0.0, 1.0, 8.0])[:count.numel()]  # no frame yet, one, the most
    return image, count


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("jitter", JITTERS)
def test_equals_the_torch_resamples(size, jitter):
    image, count = _case(sum(size), *size)
    jitter = torch.tensor([jitter])
    with _torch_ops():
        expected_mean = sample_mean_resample(image, jitter, count, 1)
        expected_plain = unjittered_resample(image, jitter, 1)
    torch.testing.assert_close(sample_mean_resample_x1(image, jitter, count), expected_mean, atol=1e-5, rtol=0)
    torch.testing.assert_close(unjittered_resample_x1(image, jitter), expected_plain, atol=1e-5, rtol=0)


@pytest.mark.parametrize("jitter", JITTERS)
def test_the_bounds_are_read_at_the_same_pixels(jitter):
    """On a black and white image the cubic read overshoots and the clamp picks 0 or 1: a bound read one pixel off
    would differ by 1, not by rounding."""
    g = torch.Generator().manual_seed(7)
    image = (torch.rand(1, 3, 37, 53, generator=g) > 0.5).float()
    jitter = torch.tensor([jitter])
    with _torch_ops():
        expected = unjittered_resample(image, jitter, 1)
    actual = unjittered_resample_x1(image, jitter)
    torch.testing.assert_close(actual, expected, atol=1e-5, rtol=0)
    assert torch.equal(actual == 0, expected == 0) and torch.equal(actual == 1, expected == 1)


def test_no_jitter_is_the_image_and_one_frame_the_plain_resample():
    image, _ = _case(3, 37, 53)
    jitter, one = torch.tensor([[0.25, -0.5]]), torch.ones(1, 1, 37, 53)
    assert torch.equal(unjittered_resample_x1(image, torch.zeros(1, 2)), image)
    # a weight of 1 blends to image + (read - image): the read up to that rounding, as in the torch path
    plain = unjittered_resample_x1(image, jitter)
    assert torch.equal(sample_mean_resample_x1(image, jitter, one), image + (plain - image))


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_split_the_rows_without_changing_them(threads):
    image, count = _case(5, 37, 53)
    jitter = torch.tensor([[0.25, -0.375]])
    single = sample_mean_resample_x1(image, jitter, count)
    torch.set_num_threads(threads)
    assert torch.equal(sample_mean_resample_x1(image, jitter, count), single)


def test_not_usable_where_the_torch_ops_must_run():
    image, count = _case(6, 4, 4)
    assert native.usable("resample", image, count)
    assert not native.usable("resample", image.double(), count)
    with _torch_ops():
        assert not native.usable("resample", image, count)
