"""The fused network's native joints equal torch's pooling, upsampling and concatenation in bfloat16."""

import pytest
import torch
import torch.nn.functional as F

from model.ops import native
from model.ops.native.unet_joints import joints_usable, mean_pool2, upsample_cat


def _image(c: int, h: int, w: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(1, c, h, w, generator=g).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)


@pytest.mark.parametrize("h,w", [(16, 16), (37, 53), (1, 3), (2, 1)])
def test_pooling_equals_torch(h, w):
    top = _image(16, h, w, 0)
    assert joints_usable(top)
    pooled = mean_pool2(top)
    assert pooled.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(pooled, F.avg_pool2d(top, 2, ceil_mode=True))  # cut windows divide by what they hold


@pytest.mark.parametrize("h,w", [(16, 16), (37, 53), (3, 1)])
def test_upsampling_with_the_concatenation_equals_torch(h, w):
    top, bottom = _image(16, h, w, 1), _image(32, (h + 1) // 2, (w + 1) // 2, 2)
    joined = upsample_cat(top, bottom)
    expected = torch.cat([top, F.interpolate(bottom, size=(h, w), mode="bilinear", align_corners=False)], dim=1)
    assert joined.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(joined[:, :16], top)
    # float arithmetic in another order may round a rare value to the neighbouring bfloat16
    difference = (joined.float() - expected.float()).abs()
    assert (difference > 0).float().mean() < 1e-3
    assert torch.all(difference <= expected.float().abs() * 2 ** -7 + 1e-30)


def test_only_bfloat16_channels_last_single_images_are_taken():
    image = _image(16, 8, 8, 3)
    assert not joints_usable(image.float())
    assert not joints_usable(image.contiguous())
    assert not joints_usable(torch.cat([image, image]))
    with native.disabled():
        assert not joints_usable(image)
