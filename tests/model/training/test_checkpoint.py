"""Checkpoints: round trip of everything training needs, atomic writes, RNG states, rebuilding the method."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
import torch

from model.training.checkpoint import capture_rng, load_checkpoint, load_method, restore_rng, save_checkpoint
from model.methods.registry import example_batch
from tests.model.training_fixtures import TinyMethod


def trained_method() -> tuple[TinyMethod, torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    torch.manual_seed(0)
    method = TinyMethod(preset="dropout")
    optimizer = torch.optim.Adam(method.parameters(), lr=0.01)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 0.5 ** step)
    frame = example_batch(8, 8, seed=1)
    for _ in range(2):
        output, _ = method.step(frame, None)
        optimizer.zero_grad()
        output.mean().backward()
        optimizer.step()
        scheduler.step()
    return method, optimizer, scheduler


def test_round_trip_keeps_everything(tmp_path):
    method, optimizer, scheduler = trained_method()
    path = save_checkpoint(tmp_path / "run" / "last.pt", method=method, optimizer=optimizer, scheduler=scheduler,
                           train_config={"method": "tiny_test:dropout", "lr": 0.01}, step=2, epoch=0.5,
                           rng=[capture_rng()], best_metric={"name": "validation/psnr", "value": 21.5, "step": 2},
                           extra={"tracking_run_id": "abc"})
    content = load_checkpoint(path)
    assert content["method"] == {"method": "tiny_test", "preset": "dropout", "scale": 1}
    assert content["step"] == 2 and content["epoch"] == 0.5
    assert content["train_config"]["lr"] == 0.01 and content["extra"] == {"tracking_run_id": "abc"}
    assert content["best_metric"]["value"] == 21.5
    for name, tensor in method.state_dict().items():
        assert torch.equal(content["model"][name], tensor)

    fresh = TinyMethod(preset="dropout")
    fresh_optimizer = torch.optim.Adam(fresh.parameters(), lr=0.01)
    fresh_scheduler = torch.optim.lr_scheduler.LambdaLR(fresh_optimizer, lambda step: 0.5 ** step)
    fresh_optimizer.load_state_dict(content["optimizer"])
    fresh_scheduler.load_state_dict(content["scheduler"])
    assert fresh_scheduler.last_epoch == 2 and fresh_optimizer.param_groups[0]["lr"] == pytest.approx(0.0025)
    first = next(iter(optimizer.state.values()))
    restored = next(iter(fresh_optimizer.state.values()))
    assert torch.equal(first["exp_avg"], restored["exp_avg"]) and int(restored["step"]) == 2


def test_load_method_rebuilds_it_in_eval_mode(tmp_path):
    method, _, _ = trained_method()
    path = save_checkpoint(tmp_path / "model.pt", method=method)
    loaded = load_method(path)
    assert isinstance(loaded, TinyMethod) and loaded.preset == "dropout" and not loaded.training
    frame = example_batch(8, 8, seed=2)
    method.eval()
    with torch.no_grad():
        torch.testing.assert_close(loaded.step(frame, None)[0], method.step(frame, None)[0], rtol=0, atol=0)


def test_rng_states_restore_every_generator():
    state = capture_rng()
    first = (torch.rand(3), np.random.rand(3), random.random())
    restore_rng(state)
    second = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(first[0], second[0]) and np.array_equal(first[1], second[1]) and first[2] == second[2]


def test_a_failed_write_leaves_the_old_checkpoint_and_no_temporary_file(tmp_path, monkeypatch):
    method, _, _ = trained_method()
    path = save_checkpoint(tmp_path / "last.pt", method=method, step=1)
    before = path.read_bytes()

    def broken_write(self, data):
        with open(self, "wb") as file:
            file.write(data[: len(data) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_bytes", broken_write)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, method=method, step=2)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


def test_bad_files_are_reported(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="expected 'denoiser-checkpoint/1'"):
        load_checkpoint(tmp_path / "foreign.pt")


def test_a_render_resolution_method_trained_at_1x_runs_at_2x_with_the_same_weights(tmp_path):
    from model.methods.base import unbounded_step
    from model.methods.baselines import bicubic_upscale
    from model.methods.registry import build_method
    from model.ops.output_bound import bound_output

    torch.manual_seed(0)
    wskpn = build_method("wskpn:xs")
    path = save_checkpoint(tmp_path / "wskpn.pt", method=wskpn)
    at_2x = load_method(path, scale=2)
    assert at_2x.scale == 2
    frame = example_batch(8, 8, seed=2)
    with torch.no_grad():
        # The output bound applies to the 2x output, after the upscale.
        expected = bound_output(bicubic_upscale(unbounded_step(wskpn.eval(), frame, None)[0], 2), frame.color)
        assert torch.allclose(at_2x.step(frame, None)[0], expected, atol=1e-6)


def test_a_scale_dependent_network_refuses_another_scale(tmp_path):
    from model.methods.registry import build_method

    path = save_checkpoint(tmp_path / "jnds.pt", method=build_method("jnds:xs", scale=2))
    with pytest.raises(ValueError, match="depends on its output scale; it cannot run at scale 1"):
        load_method(path, scale=1)


def test_the_same_weights_give_the_same_bytes_wherever_they_are_saved(tmp_path):
    # Shipped models are identified by their sha256: saving them again must not change it.
    import hashlib

    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method

    torch.manual_seed(0)
    method = build_method("wskpn:xs")
    first = save_checkpoint(tmp_path / "a.pt", method=method, step=3)
    second = save_checkpoint(tmp_path / "other" / "b.pt", method=method, step=3)
    assert hashlib.sha256(first.read_bytes()).digest() == hashlib.sha256(second.read_bytes()).digest()
