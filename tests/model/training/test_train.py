"""The training engine: exact resume, sample order, schedules, checkpoints, validation, config errors."""

from __future__ import annotations

import math

import pytest
import torch

from model.training.checkpoint import load_checkpoint, load_method
from model.data.crops import FrameCache
from model.io.dataset import Dataset
from model.ops.tonemap import display_encode
from model.training.train import (
    BEST_CHECKPOINT,
    LAST_CHECKPOINT,
    SampleStream,
    TrainConfig,
    lr_factor,
    prepare,
    train,
    validate,
)
from tests.builders import write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD

requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


class Interrupted(Exception):
    pass


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("train") / "data")


def tiny_config(data, out, **changes) -> TrainConfig:
    values = dict(method=TINY_METHOD, data=str(data), crop=8, frames_per_sample=3, batch=2, steps=4,
                  lr=0.01, warmup_steps=1, out=str(out), checkpoint_every=2, validate_every=2, device="cpu")
    values.update(changes)
    return TrainConfig(**values)


def weights(path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["model"]


def test_resumed_training_ends_with_exactly_the_uninterrupted_weights(data, tmp_path):
    # The dropout preset draws from the global RNG while training, so the RNG state must be resumed too.
    config = tiny_config(data, tmp_path / "straight", method=f"{TINY_METHOD}:dropout")
    straight = train(config)

    def stop_at_step_2(step, total, message):
        if step == 2:
            raise Interrupted

    interrupted = config.model_copy(update={"out": str(tmp_path / "interrupted")})
    with pytest.raises(Interrupted):
        train(interrupted, progress=stop_at_step_2)
    assert load_checkpoint(tmp_path / "interrupted" / LAST_CHECKPOINT)["step"] == 2
    resumed = train(interrupted)

    assert resumed["steps"] == straight["steps"] == 4
    expected, found = weights(straight["checkpoint"]), weights(resumed["checkpoint"])
    assert all(torch.equal(expected[name], found[name]) for name in expected)
    assert resumed["losses"] == straight["losses"]
    first_state = load_checkpoint(straight["checkpoint"])["optimizer"]["state"][0]
    resumed_state = load_checkpoint(resumed["checkpoint"])["optimizer"]["state"][0]
    assert torch.equal(first_state["exp_avg_sq"], resumed_state["exp_avg_sq"])

    # Without resume the same folder starts over from step 0 (resuming would refuse: step 4 >= 2 steps).
    restarted = train(interrupted.model_copy(update={"resume": False, "steps": 2}))
    assert restarted["steps"] == 2 and load_checkpoint(restarted["checkpoint"])["step"] == 2


def test_training_improves_validation_and_writes_checkpoints(data, tmp_path):
    config = tiny_config(data, tmp_path / "run", steps=6, validate_every=3, checkpoint_every=0)
    _, validation, untrained = prepare(config)
    before = validate(untrained, validation, torch.device("cpu"))
    calls = []
    result = train(config, progress=lambda *report: calls.append(report))

    assert [c[:2] for c in calls] == [(step, 6) for step in range(1, 7)]
    assert "validation PSNR" in calls[-1][2] and "loss" in calls[0][2]
    assert result["validation"]["psnr"] > before["psnr"] + 1.0
    assert result["best_metric"]["name"] == "validation/psnr" and result["best_metric"]["step"] in (3, 6)
    assert math.isfinite(result["losses"]["loss"]) and result["epochs"] == pytest.approx(6 * 2 / 5)

    last = load_checkpoint(tmp_path / "run" / LAST_CHECKPOINT)
    assert last["step"] == 6 and last["train_config"]["method"] == TINY_METHOD
    assert last["method"] == {"method": TINY_METHOD, "preset": "default", "scale": 1}
    assert len(last["rng"]) == 1
    assert (tmp_path / "run" / BEST_CHECKPOINT).is_file() == (result["best_checkpoint"] is not None)
    method = load_method(tmp_path / "run" / LAST_CHECKPOINT)
    assert validate(method, validation, torch.device("cpu"))["psnr"] == pytest.approx(result["validation"]["psnr"])


def test_sample_stream_is_a_permutation_per_epoch_and_shards_the_global_batch():
    stream = SampleStream(size=5, seed=3)
    positions = [stream.at(p) for p in range(15)]
    for epoch in range(3):
        assert sorted(index for e, index in positions if e == epoch) == list(range(5))
    assert [index for _, index in positions[:5]] != [index for _, index in positions[5:10]]
    # Step 2 of batch 4 spans epochs 1 and 2 (positions 8..11); two ranks split it, interleaved.
    global_batch = stream.batch(2, 4)
    assert global_batch == positions[8:12]
    assert stream.batch(2, 4, rank=0, world_size=2) == [positions[8], positions[10]]
    assert stream.batch(2, 4, rank=1, world_size=2) == [positions[9], positions[11]]
    assert SampleStream(size=5, seed=3).batch(2, 4) == global_batch  # no replay needed


@pytest.mark.parametrize("schedule, expected", [
    ("constant", [0.5, 1.0, 1.0, 1.0, 1.0, 1.0]),
    # After 2 warm-up steps, 4 steps of schedule: cosine over progress 0, 1/4, 2/4, 3/4; steps of 2.
    ("cosine", [0.5, 1.0, 1.0, 0.5 * (1 + math.cos(math.pi / 4)), 0.5, 0.5 * (1 + math.cos(3 * math.pi / 4))]),
    ("step", [0.5, 1.0, 1.0, 1.0, 0.1, 0.1]),
])
def test_learning_rate_schedules(schedule, expected):
    config = TrainConfig(method="m", data="d", schedule=schedule, warmup_steps=2, min_lr_ratio=0.0,
                         lr_step_every=2, lr_step_gamma=0.1)
    factor = lr_factor(config, total_steps=6)
    assert [factor(step) for step in range(6)] == pytest.approx(expected)


def test_frame_weights_skip_the_first_frames():
    config = TrainConfig(method="m", data="d", frames_per_sample=4, loss_skip_frames=1)
    assert config.frame_weights() == [0.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("changes, message", [
    ({"batch": 3, "world_size": 2}, "does not split evenly over 2 ranks"),
    ({"steps": None}, "exactly one of steps and epochs"),
    ({"steps": 10, "epochs": 2}, "exactly one of steps and epochs"),
    ({"crop": 0}, r"crop\s+Input should be greater than or equal to 1"),
    ({"schedule": "linear"}, r"schedule\s+Input should be 'cosine', 'step' or 'constant'"),
    ({"loss_skip_frames": 4}, "some frame must count"),
    ({"lr": 0.0}, r"lr\s+Input should be greater than 0"),
    ({"seed": -1}, r"seed\s+Input should be greater than or equal to 0"),
])
def test_bad_settings_name_the_field(changes, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(method="m", data="d", **changes)


def test_check_finds_fields_changed_in_place():
    config = TrainConfig(method="m", data="d")
    config.lr = -1.0
    with pytest.raises(ValueError, match=r"lr\s+Input should be greater than 0"):
        config.check()


def test_epochs_alone_replace_the_default_steps():
    config = TrainConfig(method="m", data="d", epochs=2)
    assert (config.steps, config.epochs, config.total_steps(10)) == (None, 2, 2 * math.ceil(10 / config.batch))


def test_bad_runs_fail_before_training(data, tmp_path):
    with pytest.raises(KeyError, match="unknown method 'nope'"):
        train(tiny_config(data, tmp_path / "a", method="nope"))
    with pytest.raises(ValueError, match="smaller than the 32x32 crop"):
        train(tiny_config(data, tmp_path / "a", crop=32))
    with pytest.raises(ValueError, match="unknown training settings: colour"):
        TrainConfig.from_dict({**tiny_config(data, tmp_path).to_dict(), "colour": 1})
    done = tiny_config(data, tmp_path / "done", steps=1, validate_every=0)
    train(done)
    with pytest.raises(ValueError, match="already at step 1 of 1"):
        train(done)
    with pytest.raises(ValueError, match="is a checkpoint of"):
        train(done.model_copy(update={"method": f"{TINY_METHOD}:dropout", "steps": 2}))
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            train(tiny_config(data, tmp_path / "b", device="cuda"))


def test_epochs_set_the_number_of_steps(data, tmp_path):
    result = train(tiny_config(data, tmp_path / "epochs", steps=None, epochs=1, batch=4, validate_every=0))
    assert result["steps"] == math.ceil(5 / 4)


def test_display_weight_adds_the_display_error_to_the_training_loss(data, tmp_path):
    plain = train(tiny_config(data, tmp_path / "plain", steps=1, validate_every=0))
    weighted = train(tiny_config(data, tmp_path / "display", steps=1, validate_every=0, display_weight=100.0))
    losses = weighted["losses"]
    assert "display_loss" not in plain["losses"] and losses["display_loss"] > 0
    # The same first step (same seed and weights): only the display term differs.
    assert losses["spatial_loss"] == pytest.approx(plain["losses"]["spatial_loss"])
    assert losses["loss"] == pytest.approx(plain["losses"]["loss"] + 100.0 * losses["display_loss"], rel=1e-5)


def test_validation_runs_the_protocol_metrics_over_whole_sequences(data):
    sequences = [FrameCache(sequence, 1) for sequence in Dataset(data).sequences("validation")]
    _, _, method = prepare(tiny_config(data, "unused"))
    full = validate(method, sequences, torch.device("cpu"))
    assert set(full) == {"psnr", "smape", "temporal_error"} and method.training  # the mode is put back

    # By hand: the method steps through the sequence from no history; PSNR per frame on display-encoded images.
    method.eval()
    state, psnrs = None, []
    with torch.no_grad():
        for index in range(len(sequences[0])):
            frame = sequences[0][index]
            output, state = method.step(frame.without_reference(), state)
            error = (display_encode(output) - display_encode(frame.reference)).double().square().mean()
            psnrs.append(float(10 * torch.log10(1 / error)))
    assert full["psnr"] == pytest.approx(sum(psnrs) / len(psnrs), rel=1e-5)
    first_frame_only = validate(method, sequences, torch.device("cpu"), max_frames=1)
    assert first_frame_only["psnr"] == pytest.approx(psnrs[0], rel=1e-5) and "temporal_error" not in first_frame_only


@requires_cuda
def test_training_runs_unchanged_on_a_gpu(data, tmp_path):
    result = train(tiny_config(data, tmp_path / "gpu", device="cuda"))
    cpu = train(tiny_config(data, tmp_path / "cpu"))
    assert result["steps"] == 4 and math.isfinite(result["losses"]["loss"])
    expected, found = weights(cpu["checkpoint"]), weights(result["checkpoint"])
    for name in expected:
        torch.testing.assert_close(found[name], expected[name], atol=1e-4, rtol=1e-3)


def test_method_loss_weights_and_auxiliary_loss_reach_the_training_loss(tmp_path):
    from model.training.losses import SequenceLoss
    from model.methods.base import Method
    from model.training.train import SequenceUnroll

    class WithExtra(Method):
        name = "with_extra"
        learned = True
        loss_weights = (0.2, 0.8)

        def __init__(self):
            super().__init__()
            self.gain = torch.nn.Parameter(torch.ones(()))

        def step(self, frame, state):
            return frame.color * self.gain, {"gain": self.gain.expand(1)}

        def auxiliary_loss(self, frames, states):
            return sum(s["gain"].sum() for s in states) * 0.5

    from model.methods.registry import example_batch

    frames = [example_batch(8, 8, seed=i) for i in range(3)]
    for frame in frames:
        frame.reference = frame.color * 0.5
    outputs, auxiliary = SequenceUnroll(WithExtra())(frames)
    assert float(auxiliary) == pytest.approx(1.5)
    terms = SequenceLoss(*WithExtra.loss_weights)(outputs, [f.reference for f in frames], auxiliary)
    plain = SequenceLoss(*WithExtra.loss_weights)(outputs, [f.reference for f in frames])
    assert float(terms.total) == pytest.approx(float(plain.total) + 1.5)
    assert terms.detached()["auxiliary_loss"] == pytest.approx(1.5)


def test_init_from_starts_a_fresh_run_from_another_checkpoints_weights(data, tmp_path):
    first = tiny_config(data, tmp_path / "first", steps=2, validate_every=0)
    train(first)
    source = weights(tmp_path / "first" / LAST_CHECKPOINT)
    _, _, method = prepare(tiny_config(data, tmp_path / "second", init_from=str(tmp_path / "first" / LAST_CHECKPOINT)))
    for name, value in method.state_dict().items():
        assert torch.equal(value, source[name]), name
    _, _, fresh = prepare(tiny_config(data, tmp_path / "third"))
    assert any(not torch.equal(value, source[name]) for name, value in fresh.state_dict().items())


def test_a_fine_tune_keeps_its_starting_weights_as_best_when_no_step_beats_them(data, tmp_path):
    train(tiny_config(data, tmp_path / "first", steps=6, validate_every=3))
    start = tmp_path / "first" / LAST_CHECKPOINT
    # lr 10 wrecks the weights in one step, so every later validation is worse than the starting one.
    result = train(tiny_config(data, tmp_path / "tune", steps=2, validate_every=1, lr=10.0, init_from=str(start)))
    assert result["best_metric"]["step"] == 0
    assert not result["validation"]["psnr"] >= result["best_metric"]["value"]
    best = weights(tmp_path / "tune" / BEST_CHECKPOINT)
    for name, value in weights(start).items():
        assert torch.equal(best[name], value), name
    # A run from random weights has nothing to keep: its first validation is at its first validation step.
    fresh = train(tiny_config(data, tmp_path / "fresh", steps=2, validate_every=1, lr=10.0))
    assert fresh["best_metric"]["step"] in (1, 2)


def test_init_from_refuses_another_method_or_a_missing_file(data, tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        prepare(tiny_config(data, tmp_path / "a", init_from=str(tmp_path / "missing.pt")))
    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method

    other = save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn:xs"))
    with pytest.raises(ValueError, match="holds wskpn:xs at scale 1; it cannot initialize"):
        prepare(tiny_config(data, tmp_path / "b", init_from=str(other)))


def test_init_from_loads_float32_jnds_weights_into_its_int8_preset(data, tmp_path):
    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method

    torch.manual_seed(3)
    float_method = build_method("jnds:xs", scale=2)
    path = save_checkpoint(tmp_path / "float.pt", method=float_method)
    _, _, qat = prepare(tiny_config(data, tmp_path / "qat", method="jnds:xs-int8", scale=2, init_from=str(path)))
    loaded = qat.state_dict()
    for name, value in float_method.state_dict().items():
        assert torch.equal(loaded[name], value), name


@pytest.mark.parametrize("scale", [1, 2])
def test_a_fused_model_trained_from_nothing_starts_with_the_shipped_settings(data, tmp_path, scale):
    from model.methods.fused import SHIPPED_SETTINGS

    _, _, method = prepare(tiny_config(data, tmp_path / "shipped", method="fused:fast", scale=scale))
    assert {name: getattr(method, name) for name in SHIPPED_SETTINGS[scale]} == SHIPPED_SETTINGS[scale]
    assert method.sample_mean_frames > 0 and method.stale_test_sigmas > 0
    _, _, bare = prepare(tiny_config(data, tmp_path / "bare", method="fused:fast", scale=scale,
                                     shipped_settings=False))
    assert (bare.sample_mean_frames, bare.stale_test_sigmas, bare.stale_region_pixels, bare.albedo_detail_frames,
            bare.kernel_max_pixels, bare.history_before_kernel) == (0, 0.0, 0, 0, 0, False)


def test_a_fine_tune_keeps_the_settings_of_the_model_it_starts_from(data, tmp_path):
    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method

    start = build_method("fused:fast")
    start.set_stale_test_sigmas(2.5)  # none of the others set: a fine-tune must not take the shipped ones
    path = save_checkpoint(tmp_path / "start.pt", method=start)
    _, _, tuned = prepare(tiny_config(data, tmp_path / "tune", method="fused:fast", init_from=str(path)))
    assert (tuned.stale_test_sigmas, tuned.sample_mean_frames, tuned.stale_region_pixels) == (2.5, 0, 0)


def test_a_fused_run_trained_with_the_shipped_settings_saves_and_resumes_them(data, tmp_path):
    from model.methods.fused import SHIPPED_SETTINGS

    config = tiny_config(data, tmp_path / "run", method="fused:fast", scale=2, steps=2, validate_every=0)
    train(config)
    saved = load_method(tmp_path / "run" / LAST_CHECKPOINT)
    assert {name: getattr(saved, name) for name in SHIPPED_SETTINGS[2]} == SHIPPED_SETTINGS[2]
    # A run begun without them resumes without them, whatever the option says now.
    bare = tiny_config(data, tmp_path / "bare", method="fused:fast", scale=2, steps=1, validate_every=0,
                       shipped_settings=False)
    train(bare)
    train(tiny_config(data, tmp_path / "bare", method="fused:fast", scale=2, steps=2, validate_every=0))
    resumed = load_method(tmp_path / "bare" / LAST_CHECKPOINT)
    assert (resumed.sample_mean_frames, resumed.albedo_detail_frames) == (0, 0)
