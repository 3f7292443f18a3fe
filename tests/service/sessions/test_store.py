"""service.sessions.store.SessionStore: frame-order rules, shared weights, the Redis mirror and restore, expiry, the cap."""

from __future__ import annotations

import json
import os
import threading
import uuid
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import redis
import torch
from redis.backoff import NoBackoff
from redis.retry import Retry

from core.registry import UnknownModelError
from model.deployment.inference_forms import MIN_PSNR_DB, bf16_available, form_psnr, method_key
from service.sessions.state_codec import StateFormatError, encode_state
from service.sessions.store import (
    CONTINUED,
    RESET_CAMERA_CUT,
    RESET_GAP,
    STARTED,
    FrameRejected,
    MirrorState,
    SessionLimitReached,
    SessionNotFound,
    SessionStore,
    SessionStoreUnavailable,
    state_fields,
    state_from_fields,
)
from tests.service.session_fixtures import (
    MODEL_NAME,
    FakeClock,
    ManualTimers,
    assert_same_image,
    assert_same_image_after_half_history,
    in_process_outputs,
    shared_registry,
    stream_frames,
)

def test_a_stream_gives_what_the_method_gives_in_process(make_store):
    store = make_store()
    session = store.create(MODEL_NAME, version="2")
    frames = stream_frames(6)
    expected = in_process_outputs(shared_registry().checkpoints["2"], frames)
    results = [store.process_frame(session.id, frame) for frame in frames]
    assert [r.history for r in results] == [STARTED] + [CONTINUED] * 5
    for result, image in zip(results, expected):
        assert result.output.shape == (32, 32, 3) and result.output.dtype == np.float32
        assert_same_image(result.output, image)
    assert session.frames_processed == 6 and session.next_frame_index == 6 and session.resolution == (16, 16)


@pytest.mark.skipif(not bf16_available(), reason="this CPU has no native bfloat16 convolutions")
def test_a_session_runs_the_networks_in_the_form_its_table_measured_for_the_resolution(make_store, tmp_path):
    from model.training.checkpoint import load_method
    from model.methods.base import inference_outputs

    checkpoint = shared_registry().checkpoints["2"]
    key = method_key(load_method(checkpoint))
    path = tmp_path / "forms.json"
    path.write_text(json.dumps({"methods": {key: {"16x16": {
        "chosen": "channels_last+bf16", "ms": {"eager": 2.0, "channels_last+bf16": 1.0},
        "psnr_db": {"eager": 200.0, "channels_last+bf16": 60.0}}}}}))
    frames = stream_frames(3)
    store = make_store(inference_forms=str(path))
    session = store.create(MODEL_NAME, version="2")
    outputs = [store.process_frame(session.id, frame).output for frame in frames]
    for output, in_form in zip(outputs, inference_outputs(load_method(checkpoint), frames, str(path))):
        assert_same_image(output, in_form)
    assert any(not np.array_equal(o, e) for o, e in
               zip(outputs, inference_outputs(load_method(checkpoint), frames, "off")))  # the form did run


def test_frame_index_rules(make_store):
    store = make_store()
    frames = stream_frames(8)
    reset = store.create(MODEL_NAME, on_gap="reset")
    assert store.process_frame(reset.id, frames[3]).history == STARTED  # any index starts the history
    assert store.process_frame(reset.id, frames[4]).history == CONTINUED
    with pytest.raises(FrameRejected, match="frame_index 4 repeats the last frame processed") as caught:
        store.process_frame(reset.id, frames[4])
    assert caught.value.code == "frame_out_of_order" and caught.value.details == {"expected": 5, "received": 4}
    with pytest.raises(FrameRejected, match="goes back") as caught:
        store.process_frame(reset.id, frames[1])
    assert caught.value.code == "frame_out_of_order"
    gap = store.process_frame(reset.id, frames[7])
    assert gap.history == RESET_GAP and reset.next_frame_index == 8
    # A reset gap restarts the history: the output equals a fresh start on that frame.
    assert_same_image(gap.output, store.process_frame(store.create(MODEL_NAME).id, frames[7]).output)

    reject = store.create(MODEL_NAME, on_gap="reject")
    store.process_frame(reject.id, frames[0])
    with pytest.raises(FrameRejected, match=r"skips 2 frame\(s\)") as caught:
        store.process_frame(reject.id, frames[3])
    assert caught.value.code == "frame_gap" and reject.next_frame_index == 1  # a refused frame changes nothing
    assert store.process_frame(reject.id, frames[1]).history == CONTINUED


def test_a_camera_cut_is_reported_and_drops_the_history(make_store):
    store = make_store()
    frames = stream_frames(4, cuts=(2,))
    session = store.create(MODEL_NAME, version="1")
    histories = [store.process_frame(session.id, frame).history for frame in frames]
    assert histories == [STARTED, CONTINUED, RESET_CAMERA_CUT, CONTINUED]


def test_frames_must_keep_the_session_resolution_until_a_reset(make_store):
    store = make_store()
    session = store.create(MODEL_NAME)
    store.process_frame(session.id, stream_frames(1)[0])
    larger = stream_frames(1, size=24, start=1)[0]
    with pytest.raises(FrameRejected, match="frame 1 is 24x24 but this session's frames are 16x16") as caught:
        store.process_frame(session.id, larger)
    assert caught.value.code == "resolution_mismatch"
    store.reset(session.id)
    result = store.process_frame(session.id, larger)
    assert result.history == STARTED and result.output.shape == (48, 48, 3)


def test_sessions_of_one_version_share_its_weights(make_store):
    store = make_store()
    first, second = store.create(MODEL_NAME, version="1"), store.create(MODEL_NAME, alias="champion")
    other = store.create(MODEL_NAME)  # latest: version 2
    assert first.method is second.method and other.method is not first.method
    assert (second.model.version, second.model.alias, other.model.version) == ("1", "champion", "2")
    assert not any(p.requires_grad for p in first.method.parameters()) and not first.method.training
    store.delete(first.id)
    store.delete(second.id)
    assert list(store._methods) == [("registered", MODEL_NAME, "2", None)]  # weights no session uses are released


def test_unknown_models_versions_and_aliases(make_store):
    store = make_store()
    with pytest.raises(UnknownModelError, match="model 'nope' does not exist"):
        store.create("nope")
    with pytest.raises(UnknownModelError, match="version 5 of model"):
        store.create(MODEL_NAME, version="5")
    with pytest.raises(UnknownModelError, match="has no alias 'gold'"):
        store.create(MODEL_NAME, alias="gold")
    with pytest.raises(ValueError, match="on_gap must be one of reset, reject"):
        store.create(MODEL_NAME, on_gap="skip")
    with pytest.raises(SessionNotFound):
        store.get("0" * 32)
    with pytest.raises(SessionNotFound):
        store.get("../../etc")


def test_a_history_is_stored_in_chunks_and_read_back_whole():
    base = torch.rand(1, 8, 32, 32, generator=torch.Generator().manual_seed(0))
    state = {"a": base[:, :1], "b": base[:, 1:], "valid": base[:, :1] > 0.5}
    data = encode_state(state, "float")
    fields = state_fields(data, chunk_bytes=1000)
    assert fields["state_chunks"] == -(-len(data) // 1000) > 4
    stored = {name.encode(): value if isinstance(value, bytes) else str(value).encode()
              for name, value in fields.items()}
    restored = state_from_fields(stored)
    assert set(restored) == set(state) and all(torch.equal(restored[k], state[k]) for k in state)
    assert state_from_fields({b"state_chunks": b"0"}) is None and state_fields(b"") == {"state_chunks": 0}
    del stored[b"state.2"]
    with pytest.raises(StateFormatError, match=r"lacks chunk\(s\) \[2\]"):
        state_from_fields(stored)


@pytest.mark.parametrize("precision", ["float", "half"])
def test_a_restarted_store_continues_each_session_from_redis(make_store, redis_db, precision):
    frames = stream_frames(5)
    expected = in_process_outputs(shared_registry().checkpoints["1"], frames)
    first = make_store(session_history_precision=precision)
    session = first.create(MODEL_NAME, version="1")
    for frame in frames[:3]:
        first.process_frame(session.id, frame)
    key = f"{first.prefix}{session.id}"
    assert 0 < redis_db.ttl(key) <= first.ttl_seconds

    # float16 history: outputs after the restart differ by its rounding (values near 1 lose 2^-11 of themselves).
    same = assert_same_image if precision == "float" else assert_same_image_after_half_history
    restarted = make_store(session_history_precision=precision)  # same Redis and prefix, nothing in memory
    view = restarted.get(session.id)
    assert (view.next_frame_index, view.frames_processed, view.resolution) == (3, 3, (16, 16))
    fourth = restarted.process_frame(session.id, frames[3])
    assert fourth.history == CONTINUED
    same(fourth.output, expected[3])
    assert restarted.flush(timeout=30)  # frame 3's mirror is written in the background; wait until it lands

    # The first process's memory copy is now older than Redis: it reloads before continuing, not forking.
    fifth = first.process_frame(session.id, frames[4])
    assert fifth.history == CONTINUED
    same(fifth.output, expected[4])
    assert [s.id for s in restarted.list()] == [session.id]


def observe_steps(store: SessionStore, monkeypatch) -> threading.Event:
    """An event set once a step of ``store`` has returned."""
    stepped, step = threading.Event(), store._step

    def observed_step(*args):
        result = step(*args)
        stepped.set()
        return result

    monkeypatch.setattr(store, "_step", observed_step)
    return stepped


def test_a_memory_copy_behind_redis_is_reloaded_before_it_refuses_a_frame(make_store, redis_db):
    frames = stream_frames(5)
    expected = in_process_outputs(shared_registry().checkpoints["1"], frames)
    first = make_store()
    session = first.create(MODEL_NAME, version="1", on_gap="reject")
    for frame in frames[:3]:
        first.process_frame(session.id, frame)
    assert first.flush(timeout=30)
    restarted = make_store()
    restarted.process_frame(session.id, frames[3])
    assert restarted.flush(timeout=30)
    # First's memory expects frame 3, so frame 4 is a gap it would refuse (on_gap=reject); Redis expects frame 4.
    fifth = first.process_frame(session.id, frames[4])
    assert (fifth.history, fifth.session.next_frame_index) == (CONTINUED, 5)
    assert_same_image_after_half_history(fifth.output, expected[4])  # restored from a float16 history


def test_a_frames_step_runs_while_redis_says_whether_memory_is_current(make_store, monkeypatch):
    store = make_store()
    session = store.create(MODEL_NAME)
    frames = stream_frames(2)
    store.process_frame(session.id, frames[0])
    assert store.flush(timeout=30)
    # The frame's Redis read is held until its step is done: it can only finish if the two run side by side.
    stepped = observe_steps(store, monkeypatch)
    redis_call = store._redis

    def held_redis(call):
        if threading.current_thread().name.startswith("frame"):
            assert stepped.wait(30), "the step waited for the Redis read"
        return redis_call(call)

    monkeypatch.setattr(store, "_redis", held_redis)
    with ThreadPoolExecutor(1, thread_name_prefix="frame") as pool:
        second = pool.submit(store.process_frame, session.id, frames[1]).result(timeout=60)
    assert (second.history, second.session.next_frame_index) == (CONTINUED, 2)


def redis_meta(redis_db, store: SessionStore, session_id: str) -> dict | None:
    raw = redis_db.hget(f"{store.prefix}{session_id}", "meta")
    return None if raw is None else json.loads(raw)


def test_a_frames_mirror_is_written_in_the_background_before_the_sessions_next_use(make_store, redis_db):
    store = make_store()
    session = store.create(MODEL_NAME)
    frames = stream_frames(3)
    store.process_frame(session.id, frames[0], start_mirror=False)  # as the API does: started after the response
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] is None  # not written yet
    store.start_mirror(session.id)
    assert store.flush(timeout=30)
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 1
    store.process_frame(session.id, frames[1], start_mirror=False)
    store.process_frame(session.id, frames[2], start_mirror=False)  # waits for (and starts) frame 1's write first
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 2  # at most the frame in flight is missing
    store.close()  # a clean shutdown writes what is pending
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 3


def test_a_frames_step_runs_while_the_previous_mirror_is_written_and_waits_for_it_before_answering(
        make_store, redis_db, monkeypatch):
    store = make_store()
    session = store.create(MODEL_NAME)
    frames = stream_frames(2)
    store.process_frame(session.id, frames[0], start_mirror=False)
    # Frame 0's Redis write is held open by the test, so "during the write" holds by construction.
    writing, release = threading.Event(), threading.Event()
    redis_call = store._redis

    def held_redis(call):
        if threading.current_thread().name.startswith("session-mirror") and not release.is_set():
            writing.set()
            assert release.wait(30)
        return redis_call(call)

    stepped = observe_steps(store, monkeypatch)
    monkeypatch.setattr(store, "_redis", held_redis)
    store.start_mirror(session.id)
    assert writing.wait(30)  # frame 0's history is serialized; its write is under way
    with ThreadPoolExecutor(1) as pool:
        answer = pool.submit(store.process_frame, session.id, frames[1])
        assert stepped.wait(30)  # frame 1 stepped while frame 0's write was still open
        assert not answer.done()  # ... and is not answered before that write lands
        assert redis_meta(redis_db, store, session.id)["next_frame_index"] is None
        release.set()
        assert answer.result(timeout=30).frame_index == 1
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] >= 1  # Redis lags by the frame in flight
    assert store.flush(timeout=30)
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 2


def test_with_a_mirror_interval_frames_do_not_wait_and_redis_catches_up_when_it_is_over(make_store, redis_db):
    # The interval's clock and timer are the test's: "within the interval" holds by construction, not because
    # three steps happened to take less than the interval on this machine.
    timers = ManualTimers()
    store = make_store(session_mirror_interval_seconds=0.5, mirror_timing=timers.timing)
    session = store.create(MODEL_NAME)  # creation is written at once, as always
    frames = stream_frames(4)
    store.process_frame(session.id, frames[0])  # the first frame's write starts the interval
    writer = store._writer_of(session.id)
    assert writer.wait(timeout=30)  # (test only: until that write has landed)
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 1
    for frame in frames[1:]:
        timers.advance(0.1)
        store.process_frame(session.id, frame)  # within the interval: deferred, newer ones replace older ones
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 1
    assert len(timers.pending) == 1  # one timer for the deferred writes, not one per frame
    timers.advance(0.5)
    assert timers.fire() == 1  # no more frames come: the timer writes the newest when the interval is over
    with writer._condition:
        assert writer._condition.wait_for(lambda: not writer._running and writer._pending is None, timeout=30)
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] == 4
    store.process_frame(session.id, stream_frames(1, start=4)[0])
    store.reset(session.id)  # a reset is written before it answers, interval or not
    assert redis_meta(redis_db, store, session.id)["next_frame_index"] is None


def test_a_frame_whose_mirror_never_landed_is_a_gap_after_a_restart(make_store, monkeypatch):
    frames = stream_frames(4)
    expected = in_process_outputs(shared_registry().checkpoints["1"], frames)
    first = make_store(session_history_precision="float")  # exact continuation
    session = first.create(MODEL_NAME, version="1", on_gap="reject")
    for frame in frames[:2]:
        first.process_frame(session.id, frame)
    assert first.flush(timeout=30)
    # Frame 2 is answered but its mirror never lands (Redis gone for this process, as if it died first).
    monkeypatch.setattr(first, "redis", redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2,
                                                    retry=Retry(NoBackoff(), 0)))
    assert first.process_frame(session.id, frames[2]).history == CONTINUED

    restarted = make_store(session_history_precision="float")
    with pytest.raises(FrameRejected) as caught:  # the client goes on with frame 3: a gap, not a misaligned history
        restarted.process_frame(session.id, frames[3])
    assert caught.value.code == "frame_gap" and caught.value.details == {"expected": 2, "received": 3}
    for index in (2, 3):  # resending the lost frame continues exactly
        result = restarted.process_frame(session.id, frames[index])
        assert result.history == CONTINUED
        assert_same_image(result.output, expected[index])


def test_deleting_a_session_drops_its_pending_mirror(make_store, redis_db):
    store = make_store()
    session = store.create(MODEL_NAME)
    store.process_frame(session.id, stream_frames(1)[0], start_mirror=False)
    store.delete(session.id)
    assert store.flush(timeout=30)
    assert not redis_db.exists(f"{store.prefix}{session.id}")  # no late write brought it back


def test_idle_sessions_expire(make_store, redis_db):
    clock = FakeClock()
    store = make_store(clock=clock, session_ttl_seconds=60)
    session = store.create(MODEL_NAME)
    clock.advance(59)
    store.process_frame(session.id, stream_frames(1)[0])  # use restarts the idle time
    clock.advance(59)
    assert store.get(session.id).id == session.id
    clock.advance(2)
    with pytest.raises(SessionNotFound, match="expired or deleted"):
        store.get(session.id)
    assert store.list() == [] or all(s.id != session.id for s in store.list())
    # Expired in memory, and in Redis by its TTL.
    assert 0 < redis_db.ttl(f"{store.prefix}{session.id}") <= 60


def test_the_session_cap(make_store):
    store = make_store(max_sessions=2)
    first = store.create(MODEL_NAME)
    store.create(MODEL_NAME)
    with pytest.raises(SessionLimitReached, match="2 sessions are open, the server's limit is 2") as caught:
        store.create(MODEL_NAME)
    assert caught.value.details == {"max_sessions": 2, "open": 2}
    # Sessions in Redis count too (a restarted process has none in memory yet).
    with pytest.raises(SessionLimitReached):
        make_store(max_sessions=2).create(MODEL_NAME)
    store.delete(first.id)
    store.create(MODEL_NAME)
    with pytest.raises(SessionNotFound):
        store.delete(first.id)


def test_concurrent_frames_of_one_session_are_serialized(make_store):
    store = make_store()
    session = store.create(MODEL_NAME)
    frames = stream_frames(2)
    store.process_frame(session.id, frames[0])
    outcomes, barrier = [], threading.Barrier(4)

    def post():
        barrier.wait()
        try:
            outcomes.append(store.process_frame(session.id, frames[1]).history)
        except FrameRejected as error:
            outcomes.append(error.code)

    threads = [threading.Thread(target=post) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(outcomes) == [CONTINUED] + ["frame_out_of_order"] * 3
    assert session.frames_processed == 2


class RecordedMetrics:
    """A session metrics sink (service.sessions.metrics) that keeps what it is told."""

    def __init__(self) -> None:
        self.frames: list[tuple[str, float]] = []
        self.mirror_failures: list[str] = []

    def frame_processed(self, model: str, step_seconds: float) -> None:
        self.frames.append((model, step_seconds))

    def mirror_failed(self, operation: str) -> None:
        self.mirror_failures.append(operation)


def test_sessions_keep_working_in_memory_when_redis_is_down(make_store, caplog):
    store = make_store()
    metrics, removed = RecordedMetrics(), RecordedMetrics()
    store.add_metrics(metrics)
    store.add_metrics(removed)
    store.remove_metrics(removed)
    session = store.create(MODEL_NAME)
    store.redis = redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2, socket_timeout=0.2,
                              retry=Retry(NoBackoff(), 0))  # Redis goes away
    results = [store.process_frame(session.id, frame) for frame in stream_frames(2)]
    assert [result.history for result in results] == [STARTED, CONTINUED]
    assert [s.id for s in store.list()] == [session.id]
    assert store.count() == 1  # from memory
    assert "could not mirror to Redis" in caplog.text
    assert store.flush(timeout=30)
    store.delete(session.id)
    assert metrics.frames == [(MODEL_NAME, result.inference_ms / 1000) for result in results]
    assert metrics.mirror_failures == ["write", "write", "delete"]
    assert removed.frames == [] and removed.mirror_failures == []


def test_no_session_is_created_while_redis_is_down(registry_settings):
    # Counting memory alone would let every API process (and a restarted one) go past the limit.
    down = redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2, socket_timeout=0.2,
                       retry=Retry(NoBackoff(), 0))
    store = SessionStore(registry_settings, redis_client=down, prefix="denoiser:session:test-down:")
    try:
        with pytest.raises(SessionStoreUnavailable, match="cannot be counted"):
            store.create(MODEL_NAME)
    finally:
        store.close()


def test_the_session_cap_does_not_count_sessions_idle_past_their_ttl(make_store, redis_db):
    clock = FakeClock()
    store = make_store(clock=clock, max_sessions=2, session_ttl_seconds=60)
    store.create(MODEL_NAME)
    store.create(MODEL_NAME)
    clock.advance(61)  # both idle past the TTL; their Redis keys (real time) are still there
    assert len(list(redis_db.scan_iter(match=f"{store.prefix}*"))) == 2
    assert store.list() == []
    store.create(MODEL_NAME)
    restarted = make_store(clock=clock, max_sessions=2, session_ttl_seconds=60)
    restarted.create(MODEL_NAME)  # a fresh process counts Redis alone: the two idle ones do not count either
    with pytest.raises(SessionLimitReached, match="2 sessions are open"):
        restarted.create(MODEL_NAME)


def test_every_step_runs_on_the_store_torch_thread(make_store):
    # One OpenMP team per session worker (service.sessions.torch_thread): steps asked for from different request threads all
    # run on the store's one worker here, never on the caller's.
    store = make_store(session_workers=1)
    session = store.create(MODEL_NAME)
    method = session.method
    steps: list[int] = []
    callers: list[int] = []
    original = method.step

    def recording_step(batch, state):
        steps.append(threading.get_ident())
        return original(batch, state)

    def call(frame):
        callers.append(threading.get_ident())
        store.process_frame(session.id, frame)

    method.step = recording_step
    try:
        for frame in stream_frames(4):
            caller = threading.Thread(target=call, args=(frame,))
            caller.start()
            caller.join()
    finally:
        del method.step
    assert len(steps) == 4 and len(set(steps)) == 1
    assert all(step != caller for step, caller in zip(steps, callers))
    assert session.next_frame_index == 4


def test_a_slow_session_does_not_hold_up_the_others(make_store):
    # Two session workers: session A's step is stuck (a huge frame, say) until session B's frame is done.
    store = make_store(session_workers=2, session_threads=1)
    slow, fast = store.create(MODEL_NAME, version="1"), store.create(MODEL_NAME, version="2")
    assert slow.method is not fast.method
    released, original = threading.Event(), slow.method.step

    def stuck_step(batch, state):
        assert released.wait(30), "session B's frame waited behind session A's"
        return original(batch, state)

    slow.method.step = stuck_step
    frames = stream_frames(2)
    try:
        with ThreadPoolExecutor(1) as caller:
            pending = caller.submit(store.process_frame, slow.id, frames[0])
            assert store.process_frame(fast.id, frames[0]).history == STARTED  # while A's step is still stuck
            released.set()
            assert pending.result().history == STARTED
    finally:
        released.set()
        del slow.method.step


def test_the_session_thread_budget(registry_settings):
    from service.sessions.store import session_thread_budget

    assert session_thread_budget(registry_settings.model_copy(update={"session_workers": 3,
                                                                      "session_threads": 2})) == (3, 2)
    workers, threads = session_thread_budget(registry_settings.model_copy(update={"session_workers": 2,
                                                                                  "session_threads": None}))
    assert workers == 2 and threads == max(1, (os.cpu_count() or 1) // 2)


def test_a_fused_model_streams_with_oidn_inside_and_survives_a_restart(make_store):
    # The fused family runs OIDN inside its step and carries history at the output resolution plus recurrent
    # features at render resolution: all of it must go through the session and its Redis mirror.
    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method
    from core.tracking import MLflowTracker

    registry = shared_registry()
    torch.manual_seed(5)
    method = build_method("fused:fast", scale=2)
    for parameter in method.parameters():
        parameter.data += 0.02 * torch.randn_like(parameter)
    method.set_albedo_detail_frames(8)  # as the shipped 2x models: the gathered albedo is history too
    checkpoint = save_checkpoint(registry.folder / "fused.pt", method=method)
    name = f"fused-fast-x2-{uuid.uuid4().hex[:6]}"
    tracker = MLflowTracker(registry.uri, experiment="service-tests")
    tracker.start({"method": "fused:fast"})
    tracker.log_model(checkpoint, name, {"method": "fused", "preset": "fast", "scale": "2"})
    tracker.finish("FINISHED")

    frames = stream_frames(4)
    expected = in_process_outputs(checkpoint, frames)
    first = make_store()
    session = first.create(name)
    for frame, image in zip(frames[:2], expected):
        assert_same_image(first.process_frame(session.id, frame).output, image)
    assert first.flush(timeout=30)
    restarted = make_store()  # the default float16 history: its rounding, not more, reaches the output
    for frame, image in zip(frames[2:], expected[2:]):
        result = restarted.process_frame(session.id, frame)
        assert result.history == CONTINUED
        assert_same_image_after_half_history(result.output, image)


def test_a_session_keeps_its_layout_and_owner_and_its_steps_run_on_the_session_workers(make_store):
    # Both sides of a session's creation (how its frames are read, who owns it) live in its metadata: a restarted
    # store restores them from Redis, and frames without a frame index (read in a layout) still run on the session
    # worker threads, one after the other.
    import dataclasses

    from service.sessions.store import token_digest

    store = make_store(session_workers=2, session_threads=1)
    session = store.create(MODEL_NAME, version="2", layout="blender-cycles", owner_digest=token_digest("secret"))
    threads, original = [], session.method.step

    def recorded_step(batch, state):
        threads.append(threading.current_thread().name)
        return original(batch, state)

    session.method.step = recorded_step
    # Files without a frame index read as index 0: each is the session's next frame, not a repeat of frame 0.
    frames = [dataclasses.replace(frame, frame_index=0) for frame in stream_frames(3)]
    try:
        results = [store.process_frame(session.id, frame, frame_index_given=False) for frame in frames[:2]]
    finally:
        del session.method.step
    assert [(r.frame_index, r.history) for r in results] == [(0, STARTED), (1, CONTINUED)]
    assert len(threads) == 2 and all(name.startswith("session-torch") for name in threads)
    assert (store.layout(session.id), store.owner_digest(session.id)) == ("blender-cycles", token_digest("secret"))
    restarted = make_store(session_workers=2, session_threads=1)
    assert restarted.get(session.id).layout == "blender-cycles"
    assert (restarted.layout(session.id), restarted.owner_digest(session.id)) == ("blender-cycles",
                                                                                  token_digest("secret"))
    result = restarted.process_frame(session.id, frames[2], frame_index_given=False)
    assert (result.frame_index, result.history) == (2, CONTINUED)


FULL_HD = (1920, 1080)


def _full_hd_session_survives_a_restart(make_store, redis_db, model: str) -> int:
    """Two 1080p frames, a new store (a restarted API), a third frame: it continues the history and gives what
    the method gives in process, up to the float16 history. Returns how many chunks the history took in Redis."""
    from model.methods.base import inference_outputs
    from model.io.synthetic import moving_pattern_frames

    frames = moving_pattern_frames(3, FULL_HD, np.random.default_rng(0))
    first = make_store()
    session = first.create(model)
    for frame in frames[:2]:
        first.process_frame(session.id, frame)
    assert first.flush(timeout=120)
    chunks = int(redis_db.hget(f"{first.prefix}{session.id}", "state_chunks"))
    method = first._methods[session.model.origin.key]
    expected = inference_outputs(method, frames)
    result = make_store().process_frame(session.id, frames[2])
    assert result.history == CONTINUED and result.output.shape == (FULL_HD[1] * method.scale,
                                                                    FULL_HD[0] * method.scale, 3)
    form = first.forms.form_for(method_key(method), *FULL_HD) if first.forms else None
    if form is not None and form.bf16:
        # A bf16 network rounds its inputs to 8 significant bits: a history value that float16 moved by 2^-11 can
        # land on the next bf16 step, so the restored output is held to the forms' tolerance instead.
        assert form_psnr(result.output, expected[2]) >= MIN_PSNR_DB
    else:
        assert_same_image_after_half_history(result.output, expected[2])
    return chunks


def test_a_1080p_session_survives_a_restart_with_its_history_in_chunks(make_store, redis_db, monkeypatch):
    monkeypatch.setattr("service.sessions.store.STATE_CHUNK_BYTES", 4 * 1024 * 1024)  # several chunks of a cheap history
    assert _full_hd_session_survives_a_restart(make_store, redis_db, "accumulation") > 2


@pytest.mark.slow
def test_a_1080p_session_of_the_shipped_fused_model_survives_a_restart(make_store, redis_db):
    _full_hd_session_survives_a_restart(make_store, redis_db, "fused-balanced-x1")


# --- a failed mirror is retried until it lands --------------------------------------------------------------


def _snapshot(revision: int):
    from types import SimpleNamespace

    from service.sessions.store import _Snapshot

    return _Snapshot(SimpleNamespace(id="retried"), revision, "{}", None, revision)


def test_a_failed_mirror_is_retried_until_redis_takes_it_and_a_newer_one_wins():
    from service.sessions.store import _MirrorWriter

    timers, attempts, up = ManualTimers(), [], threading.Event()

    def write(snapshot) -> bool:  # a Redis that fails until the test brings it back
        attempts.append(snapshot.revision)
        return up.is_set()

    with ThreadPoolExecutor(1) as pool:
        writer = _MirrorWriter(write, pool, 0.0, timers.monotonic, timers.start, retry_delay=lambda: 5.0)
        for revision in (1, 2):
            writer.submit(_snapshot(revision))
            assert writer.wait(30)  # waits for the attempt, not for Redis: frames go on during the outage
        assert attempts == [1, 2] and writer.failed
        assert [delay for delay, _ in timers.pending] == [5.0]  # one retry timer, however many failures
        timers.fire()  # still down: tried again, and a new timer
        assert writer.wait(30) and attempts == [1, 2, 2] and len(timers.pending) == 1
        up.set()
        timers.fire()  # back: the newest snapshot lands, nothing is left to retry
        assert writer.wait(30) and attempts == [1, 2, 2, 2] and not writer.failed and not timers.pending

        up.clear()
        writer.submit(_snapshot(3))
        assert writer.wait(30) and writer.failed
        up.set()
        writer.submit(_snapshot(4))  # a newer frame's mirror before the retry: it replaces the failed one
        assert writer.wait(30) and not writer.failed
        timers.fire()
        assert writer.wait(30) and attempts == [1, 2, 2, 2, 3, 4]

        up.clear()
        writer.submit(_snapshot(5))
        assert writer.wait(30) and writer.failed
        up.set()
        writer.drop_failed()  # another API process wrote a newer revision: an older one must not go over it
        timers.fire()
        assert writer.wait(30) and attempts == [1, 2, 2, 2, 3, 4, 5]

        up.clear()
        writer.submit(_snapshot(6))
        assert writer.wait(30) and writer.failed
        up.set()
        writer.discard()  # the session is deleted: its failed write is never retried
        timers.fire()
        writer.retry()
        writer.submit(_snapshot(7))
        assert writer.wait(30) and attempts == [1, 2, 2, 2, 3, 4, 5, 6]


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class OwnRedis:
    """A redis-server of the test's own, on a free port, that the test stops and starts again (empty)."""

    def __init__(self) -> None:
        self.port = _free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.process = None

    def start(self) -> None:
        import subprocess
        import time

        self.process = subprocess.Popen(["redis-server", "--port", str(self.port), "--save", "", "--appendonly",
                                         "no", "--daemonize", "no"], stdout=subprocess.DEVNULL)
        client = redis.Redis(port=self.port)
        for _ in range(200):  # until it accepts connections (it starts in milliseconds)
            try:
                client.ping()
                return
            except redis.ConnectionError:
                time.sleep(0.05)
        raise RuntimeError(f"redis-server on port {self.port} did not start")

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            self.process.wait(30)
            self.process = None


@pytest.fixture
def own_redis():
    import shutil

    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed")
    server = OwnRedis()
    server.start()
    yield server
    server.stop()


def test_an_idle_sessions_history_reaches_redis_once_it_is_back_and_a_restart_continues_it(make_store, own_redis):
    import time

    frames = stream_frames(40)
    expected = in_process_outputs(shared_registry().checkpoints["1"], frames)  # the uninterrupted run
    first = make_store(redis_url=own_redis.url, session_history_precision="float")
    session = first.create(MODEL_NAME, version="1", on_gap="reject")
    for frame in frames[:10]:
        first.process_frame(session.id, frame)
    assert first.flush(timeout=30)
    assert session.mirror_state() == MirrorState(True, 9, None)

    own_redis.stop()
    results = [first.process_frame(session.id, frame) for frame in frames[10:30]]
    assert {result.history for result in results} == {CONTINUED}
    state = session.mirror_state()
    assert (state.current, state.last_written_frame) == (False, 9) and state.pending_since is not None

    own_redis.start()  # empty (no persistence): only the retry can bring the session back
    # The client pauses: no request reaches the store, so only the retry timer writes the mirror.
    deadline = time.monotonic() + 60
    while not session.mirror_state().current and time.monotonic() < deadline:
        time.sleep(0.05)
    assert session.mirror_state() == MirrorState(True, 29, None)
    assert json.loads(redis.Redis.from_url(own_redis.url).hget(f"{first.prefix}{session.id}", "meta"))[
        "next_frame_index"] == 30

    restarted = make_store(redis_url=own_redis.url, session_history_precision="float")  # a new API process
    for index in range(30, 40):
        result = restarted.process_frame(session.id, frames[index])
        assert result.history == CONTINUED
        assert_same_image(result.output, expected[index])


def _partitioned() -> redis.Redis:
    """A client whose every call fails at once: this store's process has lost Redis (the others have not)."""
    return redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2, socket_timeout=0.2,
                       retry=Retry(NoBackoff(), 0))


def _until(condition, what: str, seconds: float = 60) -> None:
    import time

    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _diverged_replicas(make_store, seed: int):
    """Two replicas of one session: A loses Redis and serves frame 3 from memory (its mirror fails); the proxy sends
    the session to B, which serves a different frame 3 from Redis, so both copies hold revision 4. Returns A, B,
    A's client to Redis, the session id, A's copy, frame 4 and the outputs of the stream that B's history holds."""
    frames = stream_frames(5, seed=seed)
    other_third = stream_frames(4, seed=seed + 100)[3]
    checkpoint = shared_registry().checkpoints["1"]
    expected = in_process_outputs(checkpoint, [*frames[:3], other_third, frames[4]])
    assert not np.allclose(expected[4], in_process_outputs(checkpoint, frames)[4], atol=1e-3)  # histories differ
    a = make_store(session_history_precision="float")
    session = a.create(MODEL_NAME, version="1")
    for frame in frames[:3]:
        a.process_frame(session.id, frame)
    assert a.flush(timeout=30)
    reachable, a.redis = a.redis, _partitioned()
    a_copy = a.process_frame(session.id, frames[3]).session
    b = make_store(session_history_precision="float")
    assert_same_image(b.process_frame(session.id, other_third).output, expected[3])
    assert b.flush(timeout=30)
    return a, b, reachable, session.id, a_copy, frames[4], expected


def test_a_copy_another_api_process_moved_past_is_neither_stepped_nor_written_back(make_store, redis_db):
    a, b, reachable, session_id, a_copy, fourth, expected = _diverged_replicas(make_store, seed=3)
    b_meta = redis_meta(redis_db, b, session_id)
    assert b_meta["revision"] == a_copy.revision == 4
    # A's Redis is back: its failed mirror's retry finds B's revision there and is refused, so A drops its copy
    # (before, the retry replaced B's history with A's, and A's equal revision passed for current).
    a.redis = reachable
    _until(lambda: a_copy.superseded, "A's mirror was not retried")
    assert redis_meta(redis_db, b, session_id) == b_meta
    assert redis_db.hget(f"{b.prefix}{session_id}", "writer").decode() == f"{b.instance}:4"
    fifth = a.process_frame(session_id, fourth)  # A continues B's history, from Redis
    assert (fifth.history, fifth.session.next_frame_index) == (CONTINUED, 5)
    assert_same_image(fifth.output, expected[4])
    assert a.flush(timeout=30)
    assert redis_db.hget(f"{a.prefix}{session_id}", "writer").decode() == f"{a.instance}:5"


def test_a_copy_is_not_stepped_when_redis_holds_another_processes_revision_of_the_same_number(make_store, redis_db,
                                                                                              monkeypatch):
    # A's retry has not run yet when its next frame comes: the frame's own Redis read sees that the revision there,
    # though numbered like A's, was written by B.
    a, _, reachable, session_id, _, fourth, expected = _diverged_replicas(make_store, seed=4)
    monkeypatch.setattr(a, "_retry_failed_mirrors", lambda: None)  # the retry comes later (its timer is 5 s away)
    a.redis = reachable
    a._redis_paused_until = 0.0  # Redis answers A again now
    fifth = a.process_frame(session_id, fourth)
    assert (fifth.history, fifth.session.next_frame_index) == (CONTINUED, 5)
    assert_same_image(fifth.output, expected[4])


def test_a_session_deleted_by_another_api_process_is_not_written_back(make_store, redis_db):
    a = make_store()
    session = a.create(MODEL_NAME)
    frames = stream_frames(2)
    a.process_frame(session.id, frames[0])
    assert a.flush(timeout=30)
    reachable, a.redis = a.redis, _partitioned()
    a_copy = a.process_frame(session.id, frames[1]).session  # its mirror fails: memory is A's only record
    b = make_store()
    b.delete(session.id)
    a.redis = reachable
    _until(lambda: a_copy.superseded, "A's mirror was not retried")
    assert not redis_db.exists(f"{a.prefix}{session.id}")
    with pytest.raises(SessionNotFound):
        a.get(session.id)


def test_delete_markers_under_a_longer_prefix_are_not_counted_as_sessions(make_store, registry_settings, redis_db):
    outer = make_store()
    kept = outer.create(MODEL_NAME)
    inner = SessionStore(registry_settings, prefix=f"{outer.prefix}inner:")
    try:
        deleted = inner.create(MODEL_NAME)
        inner.delete(deleted.id)
        assert redis_db.exists(f"{outer.prefix}inner-deleted:{deleted.id}")  # a string key the outer scan meets
    finally:
        inner.close()
    restarted = make_store()  # nothing in memory: it counts what Redis holds
    assert restarted.count() == 1 and [s.id for s in restarted.list()] == [kept.id]


def test_a_read_of_redis_made_before_this_copys_write_landed_still_finds_the_copy_current(make_store, redis_db,
                                                                                          monkeypatch):
    # A continues a session B wrote last; A's mirror of its next frame lands while a request reads Redis: the read
    # shows B's revision (what A loaded), the copy already records its own. Neither a view nor a frame may take the
    # copy for stale (a frame would reload B's older revision and restart the history at a gap).
    frames = stream_frames(4)
    a = make_store()
    session = a.create(MODEL_NAME)
    a.process_frame(session.id, frames[0])
    assert a.flush(timeout=30)
    b = make_store()
    b.process_frame(session.id, frames[1])
    assert b.flush(timeout=30)
    before = redis_db.hmget(f"{a.prefix}{session.id}", "meta", "writer")
    third = a.process_frame(session.id, frames[2])
    assert a.flush(timeout=30)
    redis_call, reads = a._redis, []

    def first_read_before_the_write(call):
        if not reads:
            reads.append(call)
            return before
        return redis_call(call)

    monkeypatch.setattr(a, "_redis", first_read_before_the_write)
    view = a.get(session.id)
    assert view is third.session and view.frames_processed == 3
    reads.clear()
    fourth = a.process_frame(session.id, frames[3])
    assert reads and fourth.session is third.session and fourth.history == CONTINUED
