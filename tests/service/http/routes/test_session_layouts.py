"""Sessions read frames in a layout: raw Blender multilayer files, extra channels, a missing jitter or frame index."""

from __future__ import annotations

import numpy as np
import pytest

from model.io.exr import decode_image_exr
from model.layouts.builtin import BLENDER_CYCLES
from tests.builders import error_message
from tests.model.layouts.exr_builders import BLENDER_ORBIT, BLENDER_ORBIT_4_5, blender_like_bomb, bundle_channels, \
    write_channels
from tests.service.session_fixtures import api, create, post_frame, stream_frames  # noqa: F401 (api: a fixture)


@pytest.mark.parametrize("clip", [BLENDER_ORBIT, BLENDER_ORBIT_4_5], ids=["blender-5.0", "blender-4.5"])
def test_raw_blender_cycles_files_stream_through_a_blender_cycles_session(api, clip):  # noqa: F811
    client, _ = api()
    session = create(client, layout="blender-cycles")
    assert session["layout"] == "blender-cycles"
    paths = sorted(clip.glob("frame_*.exr"))  # Blender 4.x names the albedo passes DiffCol and GlossCol
    answers = [post_frame(client, session["id"], path.read_bytes()) for path in paths]
    assert [r.status_code for r in answers] == [200] * len(paths), answers[0].text
    # Blender's frame numbers, from 1
    assert [r.headers["X-Frame-Index"] for r in answers] == [str(index + 1) for index in range(len(paths))]
    assert [r.headers["X-History"] for r in answers] == ["started"] + ["continued"] * (len(paths) - 1)
    assert all("X-Ignored-Channels" not in r.headers and "X-Repairs" not in r.headers for r in answers)
    assert all(np.isfinite(decode_image_exr(r.content)).all() for r in answers)
    # The same files in a session of our own layout: refused, naming the layout to use.
    plain = create(client)["id"]
    message = error_message(post_frame(client, plain, (clip / "frame_0000.exr").read_bytes()), 400,
                       "invalid_frame")
    assert "layout 'denoiser' reads it from color.R" in message and "blender-cycles" in message


def test_frames_without_frame_index_or_jitter_and_with_extra_channels(api, tmp_path):  # noqa: F811
    client, _ = api()
    sid = create(client)["id"]
    bodies = []
    for index, frame in enumerate(stream_frames(2)):
        channels = bundle_channels(frame)
        channels["position.X"] = frame.depth  # an extra AOV
        path = write_channels(tmp_path / f"{index}.exr", channels)  # no frame_index, no jitter
        bodies.append(path.read_bytes())
    answers = [post_frame(client, sid, body) for body in bodies]
    assert [r.status_code for r in answers] == [200, 200], answers[1].text
    # A missing frame index is the next frame, not frame 0 again (which was 409 frame_out_of_order).
    assert [r.headers["X-Frame-Index"] for r in answers] == ["0", "1"]
    assert answers[1].headers["X-History"] == "continued"
    assert answers[0].headers["X-Ignored-Channels"] == "position.X"
    assert answers[0].headers["X-Repairs"] == "jitter: no 'jitter' attribute, read as 0 (samples at the pixel centres)"


def test_a_layout_object_is_accepted_and_an_unknown_name_is_422(api):  # noqa: F811
    client, _ = api()
    mine = dict(BLENDER_CYCLES, name="my-blender")
    session = create(client, layout=mine)
    assert session["layout"]["name"] == "my-blender"
    answer = post_frame(client, session["id"], (BLENDER_ORBIT / "frame_0001.exr").read_bytes())
    assert answer.status_code == 200, answer.text
    response = client.post("/sessions", json={"model": "x", "layout": "arnold"})
    assert response.status_code == 422 and "unknown layout 'arnold'" in response.text
    response = client.post("/sessions", json={"model": "x", "layout": {"name": "x", "channels": {"color": ["R"]}}})
    assert response.status_code == 422 and "channels.color must be a list of 3 channel names" in response.text


@pytest.mark.parametrize("layout", ["blender-cycles", "generic"])
def test_a_frame_declaring_too_many_pixels_is_413_before_decoding_in_the_sessions_layout(api, monkeypatch,  # noqa: F811
                                                                                         layout):
    import model.io.exr

    client, _ = api(max_frame_pixels=1024)
    sid = create(client, layout=layout)["id"]
    if layout == "blender-cycles":  # the fixture's 32x32 frame, 6 parts (one per pass), is within the limit
        assert post_frame(client, sid, (BLENDER_ORBIT / "frame_0000.exr").read_bytes()).status_code == 200
    decoded = []
    monkeypatch.setattr(model.io.exr, "_read_coalesced", lambda *args: decoded.append(args))
    message = error_message(post_frame(client, sid, blender_like_bomb(1024, 1024)), 413, "frame_too_large")
    assert "declares 1024x1024 = 1048576 pixels; the limit is 1024 pixels per frame" in message
    message = error_message(post_frame(client, sid, blender_like_bomb(1024, 1024, pass_size=(32, 32))), 413,
                       "frame_too_large")
    assert "in part 'ViewLayer.Depth'" in message  # a pass part past the limit, though the first part is within it
    assert decoded == []
    assert client.get(f"/sessions/{sid}").json()["frames_processed"] == (1 if layout == "blender-cycles" else 0)


def test_an_owned_session_in_a_layout_keeps_both_across_a_restart(api):  # noqa: F811
    client, store = api(session_owner_tokens=True)
    session = create(client, layout="blender-cycles")
    assert session["layout"] == "blender-cycles" and session["token"]
    sid, mine = session["id"], {"X-Session-Token": session["token"], "Content-Type": "image/x-exr"}
    files = sorted(BLENDER_ORBIT.glob("frame_*.exr"))
    error_message(post_frame(client, sid, files[0].read_bytes()), 403, "session_forbidden")
    first = client.post(f"/sessions/{sid}/frames", content=files[0].read_bytes(), headers=mine)
    assert first.status_code == 200, first.text
    assert first.headers["X-Frame-Index"] == "1"  # read in the session's layout: Blender's frame number
    assert store.flush(timeout=30)
    restarted, _ = api(session_owner_tokens=True)
    error_message(restarted.get(f"/sessions/{sid}"), 403, "session_forbidden")
    assert restarted.get(f"/sessions/{sid}", headers=mine).json()["layout"] == "blender-cycles"
    second = restarted.post(f"/sessions/{sid}/frames", content=files[1].read_bytes(), headers=mine)
    assert second.status_code == 200, second.text
    assert (second.headers["X-Frame-Index"], second.headers["X-History"]) == ("2", "continued")
