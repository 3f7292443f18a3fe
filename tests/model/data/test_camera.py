"""Camera geometry: jitter sequence, look-at frames identical to Mitsuba's, projection."""

from __future__ import annotations

import numpy as np
import pytest

from model.data.camera import Camera, frame_jitter, halton, look_at
from tests.model.data.conftest import requires_llvm


def test_halton_known_values():
    assert [halton(i, 2) for i in (1, 2, 3, 4)] == [0.5, 0.25, 0.75, 0.125]
    assert halton(1, 3) == pytest.approx(1 / 3) and halton(2, 3) == pytest.approx(2 / 3)


def test_jitter_is_halton_minus_half_and_in_range():
    assert frame_jitter(0) == pytest.approx((0.0, 1 / 3 - 0.5))
    values = np.array([frame_jitter(i) for i in range(64)])
    assert values.min() >= -0.5 and values.max() < 0.5
    assert len({tuple(v) for v in values}) == 64


@requires_llvm
def test_look_at_matches_mitsuba():
    from model.data.mitsuba_backend import load_mitsuba

    mi = load_mitsuba()
    origin, target, up = (1.0, 2.0, 3.0), (-0.5, 0.2, 0.1), (0.0, 1.0, 0.0)
    expected = np.array(mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up).matrix)
    np.testing.assert_allclose(look_at(origin, target, up), expected, atol=1e-6)


def test_projection_of_the_view_axis_is_the_image_centre_and_directions_flip():
    camera = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov=90.0)
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 4.0], [0.0, 1.0, 4.0], [0.0, 0.0, 6.0]])
    positions, in_front = camera.project(points, 100, 50)
    np.testing.assert_allclose(positions[0], [50.0, 25.0])
    # Looking down -z with +y up: world +x is image right (90 degree fov: 1 unit at distance 1 = half width).
    np.testing.assert_allclose(positions[1], [100.0, 25.0])
    np.testing.assert_allclose(positions[2], [50.0, 25.0 - 50.0])
    assert in_front.tolist() == [True, True, True, False]


def test_parallel_up_vector_is_rejected():
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 0), (0, 1, 0), (0, 1, 0))
