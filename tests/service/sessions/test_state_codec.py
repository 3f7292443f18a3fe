"""State codec: exact for masks and integers, float16 within its precision where in range, float32 otherwise."""

from __future__ import annotations

import pytest
import torch

from service.sessions import state_codec
from service.sessions.state_codec import CompressionMemo, StateFormatError, decode_state, encode_state


def sample_state() -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return {
        "history": torch.rand(1, 3, 16, 20, generator=generator),  # x / (1 + x) values in [0, 1)
        "radiance": torch.rand(1, 3, 8, 8, generator=generator) * 1e5,  # past float16's 65504
        "valid": torch.rand(1, 1, 16, 20, generator=generator) > 0.3,
        "count": torch.randint(0, 40, (1, 1, 16, 20), generator=generator, dtype=torch.int64),
        "weights": torch.rand(2, 5, generator=generator, dtype=torch.float64),
        "feature": torch.randn(1, 4, 6, 6, generator=generator).to(torch.bfloat16),
        "empty": torch.zeros(0, 3),
    }


def test_half_precision_round_trip_keeps_dtypes_shapes_and_float16_accuracy():
    state = sample_state()
    restored = decode_state(encode_state(state, "half"))
    assert list(restored) == list(state)
    for name, tensor in state.items():
        assert restored[name].dtype == tensor.dtype and restored[name].shape == tensor.shape, name
    for exact in ("valid", "count", "feature", "empty", "radiance"):  # radiance is out of float16's range
        assert torch.equal(restored[exact], state[exact]), exact
    for name in ("history", "weights"):  # float16: 11 significant bits
        torch.testing.assert_close(restored[name], state[name], rtol=2.0 ** -11, atol=2.0 ** -25)
        assert not torch.equal(restored[name], state[name])


def test_float_precision_is_lossless():
    state = sample_state()
    restored = decode_state(encode_state(state, "float"))
    assert all(torch.equal(restored[name], tensor) for name, tensor in state.items())


def test_half_precision_roughly_halves_float32_history_and_masks_are_bit_packed():
    history = {"history": torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(1))}
    assert len(encode_state(history, "half")) < 0.55 * len(encode_state(history, "float"))
    mask = {"valid": torch.ones(1, 1, 64, 64, dtype=torch.bool)}
    assert len(encode_state(mask)) < 64 * 64 / 8 + 200


def test_non_finite_values_keep_float32():
    state = {"history": torch.tensor([1.0, float("nan"), float("inf"), -2.0])}
    restored = decode_state(encode_state(state, "half"))["history"]
    assert restored.dtype == torch.float32 and torch.equal(restored.isnan(), state["history"].isnan())
    assert restored[2] == float("inf") and restored[3] == -2.0


def test_no_history_is_empty_bytes():
    assert encode_state(None) == b"" and decode_state(b"") is None and decode_state(None) is None


def test_damaged_bytes_raise_a_clear_error():
    data = encode_state(sample_state())
    with pytest.raises(StateFormatError, match="marker"):
        decode_state(b"PK\x03\x04" + data[4:])
    with pytest.raises(StateFormatError, match="cut short|damaged"):
        decode_state(data[:-10])
    with pytest.raises(StateFormatError, match="after its last tensor"):
        decode_state(data + b"\x00")
    with pytest.raises(ValueError, match="precision"):
        encode_state(sample_state(), "quarter")


def test_the_previous_frames_geometry_stays_exact_in_half_precision():
    generator = torch.Generator().manual_seed(2)
    state = {"depth": torch.rand(1, 1, 8, 8, generator=generator) * 4 + 1,
             "normal": torch.nn.functional.normalize(torch.randn(1, 3, 8, 8, generator=generator), dim=1),
             "jitter": torch.rand(1, 2, generator=generator) - 0.5}
    restored = decode_state(encode_state(state, "half"))
    assert all(torch.equal(restored[name], tensor) for name, tensor in state.items())


def noise_plane(seed: int) -> torch.Tensor:
    return torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(seed))  # 6 kB in float16: probed


def test_a_memo_skips_the_probe_of_a_plane_that_did_not_compress_until_it_is_due_again(monkeypatch):
    probes = []
    real_probe = state_codec._worth_compressing
    monkeypatch.setattr(state_codec, "_worth_compressing", lambda raw: probes.append(len(raw)) or real_probe(raw))
    memo = CompressionMemo(reprobe_every=4)
    for frame in range(10):  # probed on the 1st and the 6th: 4 encodes skip it after each probe
        state = {"history": noise_plane(frame)}
        assert torch.equal(decode_state(encode_state(state, "float", memo))["history"], state["history"])
    assert len(probes) == 2
    probes.clear()
    for frame in range(3):
        encode_state({"history": noise_plane(frame)}, "float")  # no memo: every encode probes
    assert len(probes) == 3


def test_a_memo_follows_a_plane_that_starts_or_stops_compressing():
    memo = CompressionMemo(reprobe_every=3)
    encode_state({"history": noise_plane(0)}, "half", memo)
    zeros = {"history": torch.zeros(1, 3, 32, 32)}
    sizes = [len(encode_state(zeros, "half", memo)) for _ in range(4)]  # raw until the probe is due again
    assert sizes[0] > 6000 and sizes[-1] < 600 and sizes == sorted(sizes, reverse=True)
    assert torch.equal(decode_state(encode_state(zeros, "half", memo))["history"], zeros["history"])
    noise = {"history": noise_plane(1)}  # remembered as compressible: tried whole, kept raw
    data = encode_state(noise, "half", memo)
    assert len(data) > 32 * 32 * 3 * 2
    torch.testing.assert_close(decode_state(data)["history"], noise["history"], rtol=2.0 ** -11, atol=2.0 ** -25)
    with pytest.raises(ValueError, match="reprobe_every"):
        CompressionMemo(reprobe_every=0)
