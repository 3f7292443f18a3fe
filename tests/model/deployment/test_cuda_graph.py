"""model.deployment.cuda_graph: the bookkeeping on the CPU with a stand-in backend (structure keys, static buffers,
the capture cache, the capture split at OIDN calls, when a step runs eagerly), and on a GPU replayed graphs against
the eager step over several frames and a change of resolution."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

import model.methods.oidn as oidn
from model.deployment.cuda_graph import (CapturedStep, GraphCache, HostCall, allocate_like, capture_safe_constants,
                                         clone_tensors, copy_into, device_constant, structure_key, with_cuda_graphs)
from model.methods.registry import all_methods, build_method, example_batch


class RecordingBackend:
    """Records the calls a CUDA backend would get; 'graphs' are numbered, nothing is captured (ops run eagerly)."""

    def __init__(self):
        self.events: list[str] = []
        self.graphs = 0

    def side_stream(self):
        backend = self

        class Block:
            def __enter__(self):
                backend.events.append("stream")

            def __exit__(self, *exc):
                backend.events.append("/stream")

        return Block()

    def new_graph(self):
        self.graphs += 1
        return f"g{self.graphs - 1}"

    def begin(self, graph, pool):
        self.events.append(f"begin {graph} pool={pool}")
        return "pool"

    def end(self, graph):
        self.events.append(f"end {graph}")

    def replay(self, graph):
        self.events.append(f"replay {graph}")

    def synchronize(self):
        self.events.append("sync")


@pytest.fixture
def denoised(monkeypatch):
    calls = []

    def fake_denoise(frame, quality):
        calls.append(quality)
        return frame.color * 0.5

    monkeypatch.setattr(oidn, "_denoise", fake_denoise)
    return calls


def test_the_key_holds_shapes_and_presence_not_values():
    frame = example_batch(8, 8, seed=0)
    assert structure_key((frame, None)) == structure_key((example_batch(8, 8, seed=1), None))
    assert structure_key((frame, None)) != structure_key((example_batch(8, 16, seed=0), None))
    assert structure_key((frame, None)) != structure_key((frame, {"history": frame.color}))
    assert structure_key((frame, {"history": frame.color})) != structure_key((frame, {"history": frame.albedo[:, :1]}))
    with_estimate = dataclasses.replace(frame, spatial_estimate=frame.color)
    assert structure_key((frame, None)) != structure_key((with_estimate, None))
    assert structure_key(frame.color) != structure_key(frame.color.contiguous(memory_format=torch.channels_last))


def test_static_buffers_are_filled_in_place_and_outputs_are_copies():
    frame = example_batch(8, 8, seed=0)
    state = {"history": torch.rand(1, 3, 8, 8)}
    static_frame, static_state = allocate_like(frame), allocate_like(state)
    kept = static_frame.color
    copy_into(static_frame, frame)
    copy_into(static_state, state)
    assert static_frame.color is kept and torch.equal(kept, frame.color)
    assert torch.equal(static_state["history"], state["history"])
    assert static_frame.camera_cut.device.type == "cpu" and not static_frame.camera_cut.any()
    other = example_batch(8, 8, seed=3)
    copy_into(static_frame, other)
    assert torch.equal(kept, other.color)
    cloned = clone_tensors(static_state)
    assert cloned["history"] is not static_state["history"] and torch.equal(cloned["history"], state["history"])
    with pytest.raises(ValueError, match="state entries"):
        copy_into(static_state, {"other": state["history"]})


def test_the_cache_captures_on_the_second_sighting_and_keeps_the_most_recent():
    cache = GraphCache(max_graphs=2)
    assert not cache.ready("a") and cache.ready("a")
    cache.store("a", 1)
    cache.store("b", 2)
    assert cache.get("a") == 1  # now the most recent
    cache.store("c", 3)
    assert cache.get("b") is None and cache.get("a") == 1 and cache.get("c") == 3
    with pytest.raises(ValueError):
        GraphCache(max_graphs=0)


def test_constants_are_filled_on_the_device_during_a_capture_only():
    made = device_constant([[1.5, -2.0], [3.0, 4.25]], torch.float32, "cpu")
    assert torch.equal(made, torch.tensor([[1.5, -2.0], [3.0, 4.25]]))
    assert device_constant([3, 4], None, "cpu").dtype == torch.int64
    real = torch.tensor
    with capture_safe_constants():
        assert torch.tensor is not real
        assert torch.equal(torch.tensor([1.0, 2.0], device="cpu"), real([1.0, 2.0]))  # not a CUDA constant: as is
    assert torch.tensor is real


def two_oidn_calls(frame, state):
    """A step with two OIDN calls between device work, as a step with a sample mean has one."""
    first = oidn.oidn_denoise(frame, "fast")
    second = oidn.oidn_denoise(dataclasses.replace(frame, color=first + 1), "high")
    history = second if state is None else second + state["history"]
    return history * 2, {"history": history}


def test_a_capture_is_split_at_each_oidn_call_and_replayed_in_order(denoised):
    backend = RecordingBackend()
    frame = example_batch(8, 8, seed=0)
    captured, outputs = CapturedStep.capture(two_oidn_calls, frame, None, backend)
    assert backend.events == ["stream", "begin g0 pool=None", "end g0", "replay g0", "sync",
                              "begin g1 pool=pool", "end g1", "replay g1", "sync",
                              "begin g2 pool=pool", "end g2", "replay g2", "/stream"]
    assert denoised == ["fast", "high"]
    assert [type(part).__name__ for part in captured.parts] == ["str", "HostCall", "str", "HostCall", "str"]
    assert torch.tensor.__module__ == "torch"  # the capture's constant maker is gone again
    expected, _ = two_oidn_calls(frame, None)
    assert torch.allclose(outputs[0], expected)
    assert outputs[0] is not captured.outputs[0]
    # a replay copies the new frame into the static one the first OIDN call reads, and OIDN's result into its buffer
    backend.events.clear()
    new = example_batch(8, 8, seed=5)
    captured.run(new, None)
    assert backend.events == ["replay g0", "sync", "replay g1", "sync", "replay g2"]
    first: HostCall = captured.parts[1]
    assert first.frame is captured.frame and torch.allclose(first.result, new.color * 0.5)


def test_a_graphed_step_warms_up_captures_replays_and_recaptures_per_structure(denoised):
    backend = RecordingBackend()
    calls = []

    class Method(torch.nn.Module):
        def step(self, frame, state):
            calls.append(frame.color.shape[-1])
            return two_oidn_calls(frame, state)

    method = with_cuda_graphs(Method(), "cpu", max_graphs=1, backend=backend)
    graphed = method._cuda_graphs
    assert with_cuda_graphs(method, "cpu", backend=backend) is method and method._cuda_graphs is graphed
    state = None
    for index in range(4):  # no state, then the state's structure twice (warm-up, capture) and a replay
        _, state = method.step(example_batch(8, 8, seed=index), state)
    assert graphed.captures == 1
    assert calls == [8, 8, 8]  # the replay did not call the step
    assert backend.events.count("stream") == 3  # the two warm-up calls and the capture ran on the side stream
    _, wide = method.step(example_batch(8, 16, seed=9), None)
    _, wide = method.step(example_batch(8, 16, seed=10), wide)
    _, wide = method.step(example_batch(8, 16, seed=11), wide)
    assert graphed.captures == 2  # the new resolution: warm-up, then captured (the 8x8 capture evicted)
    cut = example_batch(8, 16, seed=12)
    cut.camera_cut[:] = True
    before = len(calls)
    method.step(cut, wide)
    assert len(calls) == before + 1 and graphed.captures == 2  # a cut runs eagerly


def test_a_failed_capture_leaves_that_structure_eager(denoised, caplog):
    backend = RecordingBackend()
    calls = []

    class Method(torch.nn.Module):
        def step(self, frame, state):
            calls.append(1)
            if backend.events and backend.events[-1].startswith("begin"):
                raise RuntimeError("operation not permitted when stream is capturing")
            return frame.color, None

    method = with_cuda_graphs(Method(), "cpu", backend=backend)
    for seed in range(4):
        output, _ = method.step(example_batch(8, 8, seed=seed), None)
    assert method._cuda_graphs.captures == 0 and len(calls) == 5  # the failed capture's try, then eager
    assert "capture of this step failed" in caplog.text


def test_off_cuda_the_method_is_left_as_it_is():
    method = torch.nn.Module()
    assert with_cuda_graphs(method, "cpu") is method and not hasattr(method, "_cuda_graphs")


requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _cuda_frames(count, size, seed):
    from model.io.synthetic import moving_pattern_frames
    from model.methods.base import FrameBatch

    return [FrameBatch.from_bundles([bundle], scale=None).to("cuda")
            for bundle in moving_pattern_frames(count, size, np.random.default_rng(seed))]


@requires_cuda
@pytest.mark.parametrize("name", ["fused-fast-x1", "fused-balanced-x2"])
def test_graph_replays_equal_the_eager_step_on_cuda_across_a_resolution_change(name):
    from model.deployment.inference_forms import load_form_table, with_inference_forms
    from model.deployment.pretrained import load_pretrained

    eager = load_pretrained(name, device="cuda").for_inference()
    graphed = with_inference_forms(copy.deepcopy(eager), load_form_table("measured"), "cuda")
    assert graphed._cuda_graphs is not None
    with torch.inference_mode():
        for size, seed in (((64, 48), 0), ((96, 64), 1)):
            eager_state = graphed_state = None
            for frame in _cuda_frames(6, size, seed):
                expected, eager_state = eager.step(frame, eager_state)
                output, graphed_state = graphed.step(frame, graphed_state)
                torch.testing.assert_close(output, expected, atol=1e-5, rtol=1e-5)
                for key in expected.keys() if isinstance(expected, dict) else []:
                    torch.testing.assert_close(graphed_state[key], eager_state[key])
    assert graphed._cuda_graphs.captures >= 2


@requires_cuda
@pytest.mark.parametrize("name, scale", [(f"{spec.name}:{spec.default_preset}", scale)
                                         for spec in all_methods() for scale in spec.scales])
def test_every_method_graphed_on_cuda_steps_as_it_does_eagerly(name, scale):
    # Untrained weights do: a replay must compute what the eager step computes whatever the weights. A method whose
    # capture fails runs eagerly (and says so in a warning), which equals the eager step trivially.
    torch.manual_seed(0)
    eager = build_method(name, scale=scale).eval().for_inference().to("cuda")
    graphed = with_cuda_graphs(copy.deepcopy(eager), "cuda")
    eager_state = graphed_state = None
    with torch.inference_mode():
        for seed in range(5):
            frame = example_batch(16, 16, seed=seed, device="cuda")
            expected, eager_state = eager.step(frame, eager_state)
            output, graphed_state = graphed.step(frame, graphed_state)
            torch.testing.assert_close(output, expected, atol=1e-5, rtol=1e-5)


@requires_cuda
def test_a_camera_cut_runs_eagerly_and_the_graph_resumes_after_it():
    from model.deployment.pretrained import load_pretrained

    eager = load_pretrained("fused-fast-x1", device="cuda").for_inference()
    graphed = with_cuda_graphs(copy.deepcopy(eager), "cuda")
    eager_state = graphed_state = None
    with torch.inference_mode():
        for index, frame in enumerate(_cuda_frames(8, (48, 32), 4)):
            frame.camera_cut[:] = index == 4
            expected, eager_state = eager.step(frame, eager_state)
            output, graphed_state = graphed.step(frame, graphed_state)
            torch.testing.assert_close(output, expected, atol=1e-5, rtol=1e-5)
    assert graphed._cuda_graphs.captures >= 1
