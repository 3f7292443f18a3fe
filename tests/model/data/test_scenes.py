"""The scene library covers every hard case of temporal denoising it is built for (docs/generating-data.md), and seeds
really vary the scenes."""

from __future__ import annotations

import numpy as np
import pytest

from model.data.scenes import SCENES, ImageTexture, build_scene


def test_library_has_at_least_eight_recipes_that_build_for_several_seeds():
    assert len(SCENES) >= 8
    for name in SCENES:
        for seed in range(3):
            scene = build_scene(name, seed, 5)
            assert scene.frames == 5 and all(len(o.transforms) == 5 for o in scene.objects)
            assert len({o.name for o in scene.objects}) == len(scene.objects)


def test_seeds_vary_the_scene():
    first, second = build_scene("diffuse_room", 0, 2), build_scene("diffuse_room", 1, 2)
    assert [o.material.reflectance for o in first.objects] != [o.material.reflectance for o in second.objects]
    same = build_scene("diffuse_room", 0, 2)
    assert [o.material.reflectance for o in first.objects] == [o.material.reflectance for o in same.objects]


def _moving(scene):
    return [o for o in scene.objects if not all(np.array_equal(o.transforms[0], t) for t in o.transforms)]


def _camera_step_degrees(scene, index):
    a = np.subtract(scene.cameras[index].target, scene.cameras[index].origin)
    b = np.subtract(scene.cameras[index + 1].target, scene.cameras[index + 1].origin)
    return np.degrees(np.arccos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b)))


def test_recipes_cover_the_named_hard_cases():
    kinds = {name: {o.material.kind for o in build_scene(name, 0, 8).objects} for name in SCENES}
    textured = [o for o in build_scene("textured_detail", 0, 8).objects
                if isinstance(o.material.reflectance, ImageTexture)]
    assert len(textured) >= 4
    metals = [o.material.roughness for o in build_scene("metals", 0, 8).objects if o.material.kind == "metal"]
    assert 0.0 in metals and max(metals) >= 0.3  # smooth and rough metal
    assert "glass" in kinds["glass"]

    light_scene = build_scene("moving_light", 0, 8)
    assert [o.name for o in _moving(light_scene)] == ["moving_light"] and _moving(light_scene)[0].emission
    assert len({c for c in light_scene.cameras}) == 1

    swinging = build_scene("swinging_light", 0, 8)
    lights = [o for o in swinging.objects if o.emission is not None]
    assert [o.name for o in _moving(swinging)] == ["swinging_light"] == [o.name for o in lights]
    assert len({c for c in swinging.cameras}) == 8  # the camera moves too, unlike moving_light's

    object_scene = build_scene("moving_object", 0, 8)
    assert [o.emission for o in _moving(object_scene)] == [None]

    fast = build_scene("fast_camera", 0, 8)
    assert min(_camera_step_degrees(fast, i) for i in range(7)) > 1.5

    dark = build_scene("dark_fireflies", 0, 8)
    lights = [o for o in dark.objects if o.emission is not None]
    assert len(lights) == 1 and lights[0].transforms[0][0, 0] < 0.1 and max(dark.sky) == 0.0

    cut = build_scene("camera_cut", 0, 8)
    assert cut.cuts == frozenset({4}) and cut.cameras[3] != cut.cameras[4]


def test_unknown_scene_and_bad_frame_count_are_named():
    with pytest.raises(KeyError, match="unknown scene 'nope'; known scenes: .*diffuse_room"):
        build_scene("nope", 0, 4)
    with pytest.raises(ValueError, match="frames must be >= 1"):
        build_scene("glass", 0, 0)


def _light_centre(obj, index):
    return obj.transforms[index][:3, 3]


def test_failure_mode_recipes_make_history_wrong_on_purpose():
    emitter = build_scene("visible_emitter", 0, 8)
    lamp = [o for o in _moving(emitter) if o.emission is not None]
    assert len(lamp) == 1 and len({c for c in emitter.cameras}) == 1  # a static camera: only the lamp moves
    assert abs(_light_centre(lamp[0], 7)[0] - _light_centre(lamp[0], 0)[0]) > 2.5  # it crosses the frame

    orbit = build_scene("orbiting_light", 0, 8)
    light = [o for o in orbit.objects if o.emission is not None][0]
    a, b = _light_centre(light, 0)[[0, 2]], _light_centre(light, 1)[[0, 2]]
    step = np.degrees(np.arccos(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b)))
    assert 20.0 - 1e-6 <= step <= 50.0 + 1e-6  # tens of degrees a frame

    sliding = build_scene("sliding_over_texture", 0, 8)
    assert len(_moving(sliding)) == 2 and all(o.emission is None for o in _moving(sliding))
    assert isinstance(sliding.objects[0].material.reflectance, ImageTexture)  # fine texture under them

    highlights = build_scene("moving_highlights", 0, 8)
    assert [o.name for o in _moving(highlights)] == ["glide_light"]
    assert sum(o.material.kind in ("metal", "plastic") and o.material.roughness < 0.4
               for o in highlights.objects) >= 4
