"""disocclusion_mask against a per-pixel loop and hand-built cases."""

import math

import torch

from model.ops.reproject import disocclusion_mask
from tests.builders import rand


def unit_normals(n, h, w, seed):
    v = rand(n, 3, h, w, seed=seed, lo=-1, hi=1) + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64).view(1, 3, 1, 1)
    return v / v.norm(dim=1, keepdim=True)


def naive_mask(depth, normal, prev_depth, prev_normal, motion, dtol, ctol):
    n_, _, h, w = depth.shape
    out = torch.zeros(n_, 1, h, w, dtype=torch.bool)
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                px = x + 0.5 + motion[n, 0, y, x].item()
                py = y + 0.5 + motion[n, 1, y, x].item()
                if not (0 <= px < w and 0 <= py < h):
                    continue
                sx, sy = math.floor(px), math.floor(py)  # the pixel whose footprint holds the sample
                d, pd = depth[n, 0, y, x].item(), prev_depth[n, 0, sy, sx].item()
                a, b = normal[n, :, y, x], prev_normal[n, :, sy, sx]
                cos = (a @ b / (a.norm() * b.norm())).item() if a.norm() > 0 and b.norm() > 0 else 0.0
                out[n, 0, y, x] = d > 0 and pd > 0 and abs(d - pd) <= dtol * d and cos >= ctol
    return out


def test_matches_naive_loop():
    n, h, w = 2, 12, 10
    depth = rand(n, 1, h, w, seed=1, lo=1.0, hi=2.0)
    depth[rand(n, 1, h, w, seed=2) < 0.15] = 0.0
    prev_depth = depth * rand(n, 1, h, w, seed=3, lo=0.8, hi=1.2)  # about half fail the 10% test
    normal = unit_normals(n, h, w, seed=4)
    prev_normal = unit_normals(n, h, w, seed=5)
    motion = rand(n, 2, h, w, seed=6, lo=-2.5, hi=2.5)
    got = disocclusion_mask(depth, normal, prev_depth, prev_normal, motion, 0.1, 0.9)
    ref = naive_mask(depth, normal, prev_depth, prev_normal, motion, 0.1, 0.9)
    assert got.dtype == torch.bool and got.shape == (n, 1, h, w)
    assert torch.equal(got, ref)
    assert 0 < int(ref.sum()) < ref.numel()  # the case exercises both outcomes


def _static_scene():
    depth = torch.full((1, 1, 12, 10), 4.0, dtype=torch.float64)
    depth[..., 0, 0] = 0.0  # background pixel: no surface
    normal = torch.zeros(1, 3, 12, 10, dtype=torch.float64)
    normal[:, 2] = 1.0
    return depth, normal


def test_static_scene_is_valid_wherever_there_is_a_surface():
    depth, normal = _static_scene()
    valid = disocclusion_mask(depth, normal, depth, normal, torch.zeros(1, 2, 12, 10, dtype=torch.float64))
    assert torch.equal(valid, depth > 0)


def test_each_failure_reason():
    depth, normal = _static_scene()
    zero = torch.zeros(1, 2, 12, 10, dtype=torch.float64)

    out_of_image = zero.clone()
    out_of_image[:, 0, :, -3:] = 3.0  # last 3 columns read past the right edge
    valid = disocclusion_mask(depth, normal, depth, normal, out_of_image)
    assert not bool(valid[..., -3:].any()) and bool(valid[..., 1:, :-3].all())

    prev_depth = depth.clone()
    prev_depth[..., 5, 5] *= 1.2  # 20% farther: occluder moved away
    prev_depth[..., 6, 6] *= 1.05  # 5%: within tolerance
    valid = disocclusion_mask(depth, normal, prev_depth, normal, zero)
    assert not bool(valid[..., 5, 5]) and bool(valid[..., 6, 6])

    prev_normal = normal.clone()
    prev_normal[:, :, 2, 3] = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)  # 45 degrees: cos 0.707
    prev_normal[:, :, 2, 4] = torch.tensor([0.2, 0.0, 1.0], dtype=torch.float64)  # cos 0.98, unnormalized
    valid = disocclusion_mask(depth, normal, depth, prev_normal, zero)
    assert not bool(valid[..., 2, 3]) and bool(valid[..., 2, 4])

    prev_depth = depth.clone()
    prev_depth[..., 7, 7] = 0.0  # nothing there in the previous frame
    valid = disocclusion_mask(depth, normal, prev_depth, normal, zero)
    assert not bool(valid[..., 7, 7])


def test_motion_follows_the_surface():
    # A surface at depth 2 moves 2 px right between frames: it was at x-2 in the previous frame.
    prev_depth = torch.full((1, 1, 6, 8), 9.0, dtype=torch.float64)
    prev_depth[..., 1:4, 1:3] = 2.0
    depth = torch.full((1, 1, 6, 8), 9.0, dtype=torch.float64)
    depth[..., 1:4, 3:5] = 2.0
    normal = torch.zeros(1, 3, 6, 8, dtype=torch.float64)
    normal[:, 2] = 1.0
    motion = torch.zeros(1, 2, 6, 8, dtype=torch.float64)
    motion[:, 0, 1:4, 3:5] = -2.0
    valid = disocclusion_mask(depth, normal, prev_depth, normal, motion)
    assert bool(valid[..., 1:4, 3:5].all())
    # background just uncovered where the object used to be: previous frame saw the object there
    assert not bool(valid[..., 1:4, 1:3].any())


def test_reproject_history_ignores_jitter_for_the_history_and_uses_the_jitter_change_for_geometry():
    from model.ops.reproject import reproject_history

    generator = torch.Generator().manual_seed(3)
    history = torch.rand(1, 3, 6, 7, generator=generator)
    count = torch.full((1, 1, 6, 7), 2.0)
    depth = torch.ones(1, 1, 6, 7)
    depth[..., :, 4:] = 3.0  # a depth edge between columns 3 and 4
    normal = torch.zeros(1, 3, 6, 7)
    normal[:, 2] = 1.0
    motion = torch.zeros(1, 2, 6, 7)
    jitter, previous_jitter = torch.tensor([[0.4, 0.0]]), torch.tensor([[-0.4, 0.0]])
    warped, warped_count, valid = reproject_history(history, count, depth, normal, depth, normal, motion,
                                                    jitter, previous_jitter)
    # A static camera: the history comes back where it was, whatever the jitter.
    torch.testing.assert_close(warped, history)
    torch.testing.assert_close(warped_count, count)
    # The geometry test reads the previous samples 0.8 px to the right: nearest reaches the neighbour,
    # so the column left of the edge sees the far surface and fails, and the last column reads off the image.
    assert not valid[0, 0, :, 3].any() and not valid[0, 0, :, 6].any()
    assert valid[0, 0, :, :3].all() and valid[0, 0, :, 4:6].all()
