"""model.deployment.inference_forms: every form stays within tolerance of fp32 eager, and the table picks forms by resolution."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import torch
from torch import nn

from model.deployment.inference_forms import (
    FORMS, MIN_PSNR_DB, SHIPPED_TABLE, FormTable, bf16_available, form_psnr, load_form_table, method_key, networks_of,
    _to_float32, run_networks_as, with_inference_forms)
from model.methods.base import FrameBatch
from model.methods.registry import build_method, method_spec
from model.io.synthetic import moving_pattern_frames

needs_bf16 = pytest.mark.skipif(not bf16_available(), reason="this CPU has no native bfloat16 convolutions")


def frames(size: int, count: int = 3) -> list[FrameBatch]:
    bundles = moving_pattern_frames(count, (size, size), np.random.default_rng(3))
    return [FrameBatch.from_bundles([bundle], scale=None) for bundle in bundles]


def stream(method, batches, form=None) -> list[torch.Tensor]:
    outputs, state = [], None
    with torch.no_grad():
        for batch in batches:
            if form is None:
                output, state = method.step(batch, state)
            else:
                with run_networks_as(method, form):
                    output, state = method.step(batch, state)
            outputs.append(output)
    return outputs


def seeded(text: str, scale: int):
    torch.manual_seed(0)
    return build_method(text, scale).eval().for_inference()


def table(rows: dict, **extra) -> FormTable:
    return FormTable({"methods": rows, **extra})


def row(chosen: str, ms: dict[str, float], psnr: dict[str, float] | None = None) -> dict:
    return {"chosen": chosen, "ms": ms, "psnr_db": psnr or {name: 200.0 for name in ms}}


@pytest.mark.parametrize("text,scale", [("wskpn:xs", 1), ("afn:xs", 1), ("munet:xs", 2), ("jnds:xs", 2)])
def test_channels_last_gives_the_eager_output(text, scale):
    method = seeded(text, scale)
    batches = frames(32)
    for eager, fast in zip(stream(method, batches), stream(method, batches, "channels_last")):
        torch.testing.assert_close(fast, eager, rtol=1e-4, atol=1e-5)


@needs_bf16
@pytest.mark.parametrize("text,scale", [("wskpn:xs", 1), ("afn:xs", 1), ("munet:xs", 2), ("jnds:xs", 2)])
def test_bf16_networks_stay_within_the_stated_tolerance_and_the_rest_stays_float32(text, scale):
    method = seeded(text, scale)
    batches = frames(32)
    eager = stream(method, batches)
    with torch.no_grad(), run_networks_as(method, "channels_last+bf16"):
        state = None
        for batch, expected in zip(batches, eager):
            output, state = method.step(batch, state)
            assert output.dtype == torch.float32
            assert all(value.dtype != torch.bfloat16 for value in state.values())  # histories stay float32
            assert form_psnr(output, expected) >= MIN_PSNR_DB
    # ... and the difference is there: the form really ran in bf16 (a test of "no change" could not fail).
    assert any(not torch.equal(a, b) for a, b in zip(eager, stream(method, batches, "bf16")))


def test_the_table_takes_the_row_of_the_nearest_resolution_in_pixels():
    forms = table({"wskpn:s:x1": {"128x128": row("bf16", {"eager": 10, "bf16": 5}),
                                  "512x512": row("channels_last", {"eager": 10, "channels_last": 6}),
                                  "1920x1080": row("eager", {"eager": 10})}})
    assert forms.form_for("wskpn:s:x1", 100, 100, bf16=True).name == "bf16"
    assert forms.form_for("wskpn:s:x1", 400, 300, bf16=True).name == "channels_last"  # 120k px: nearer 512^2
    assert forms.form_for("wskpn:s:x1", 1280, 720, bf16=True).name == "eager"
    assert forms.form_for("afn:m:x1", 128, 128, bf16=True).name == "eager"  # no row: eager


def test_a_bf16_choice_falls_back_to_the_fastest_form_without_bf16_on_a_cpu_without_it():
    forms = table({"k:s:x1": {"128x128": row("channels_last+bf16", {"eager": 10, "channels_last": 8, "bf16": 6,
                                                                   "channels_last+bf16": 5})}})
    assert forms.form_for("k:s:x1", 128, 128, bf16=True).name == "channels_last+bf16"
    assert forms.form_for("k:s:x1", 128, 128, bf16=False).name == "channels_last"


def test_a_form_below_the_tolerance_or_compiled_is_not_taken_unless_allowed():
    rows = {"k:s:x1": {"64x64": row("compile", {"eager": 10, "bf16": 4, "compile": 3},
                                     {"eager": 200, "bf16": MIN_PSNR_DB - 1, "compile": 200})}}
    assert table(rows).form_for("k:s:x1", 64, 64, bf16=True).name == "eager"
    assert table(rows, allow_compile=True).form_for("k:s:x1", 64, 64, bf16=True).name == "compile"


def test_a_method_steps_in_the_form_of_each_frames_resolution():
    method = seeded("wskpn:xs", 1)
    seen: list[torch.dtype] = []
    first_conv = next(m for m in networks_of(method)[0].modules() if isinstance(m, nn.Conv2d))
    first_conv.register_forward_hook(lambda module, inputs, output: seen.append(output.dtype))
    key = method_key(method)
    with_inference_forms(method, table({key: {"32x32": row("bf16", {"eager": 10, "bf16": 5}),
                                              "64x64": row("eager", {"eager": 10})}}))
    with torch.no_grad():
        for size in (32, 64, 32):
            method.step(frames(size, 1)[0], None)
    expected_small = torch.bfloat16 if bf16_available() else torch.float32
    assert seen == [expected_small, torch.float32, expected_small]


def test_each_thread_runs_its_own_form():
    method = seeded("wskpn:xs", 1)
    batch = frames(32, 1)[0]
    entered, done = threading.Event(), threading.Event()
    dtypes: dict[str, torch.dtype] = {}
    conv = next(m for m in networks_of(method)[0].modules() if isinstance(m, nn.Conv2d))
    conv.register_forward_hook(lambda module, inputs, output: dtypes.__setitem__(
        threading.current_thread().name, output.dtype))

    def other() -> None:
        with run_networks_as(method, "bf16"):
            entered.set()
            assert done.wait(30)  # holds its form while the main thread steps

    thread = threading.Thread(target=other, name="other")
    thread.start()
    assert entered.wait(30)
    with torch.no_grad():
        method.step(batch, None)  # this thread selected nothing: eager
    done.set()
    thread.join(30)
    assert dtypes[threading.current_thread().name] == torch.float32


def test_tables_are_read_or_refused_with_the_reason(tmp_path):
    assert load_form_table("off") is None and load_form_table(None) is None
    with pytest.raises(ValueError, match="cannot read the inference form table"):
        load_form_table(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text(json.dumps({"rows": []}))
    with pytest.raises(ValueError, match="no 'methods' object"):
        load_form_table(tmp_path / "bad.json")


def test_the_shipped_table_names_registered_methods_and_known_forms_within_tolerance():
    shipped = load_form_table("measured")
    assert load_form_table(SHIPPED_TABLE).keys() == shipped.keys()
    for key in shipped.keys():
        name, preset, scale = key.split(":")
        spec = method_spec(name)
        assert preset in spec.presets and int(scale[1:]) in spec.scales, key
        for size, measured in shipped.data["methods"][key].items():
            assert measured["chosen"] in FORMS, (key, size)
            assert measured["psnr_db"][measured["chosen"]] >= MIN_PSNR_DB, (key, size)
            assert not FORMS[measured["chosen"]].compiled or shipped.allow_compile


def test_bf16_outputs_come_back_as_contiguous_float32_with_their_values():
    # a channels_last network's outputs are strided slices; later per-channel reads are faster on contiguous ones
    head = torch.rand(1, 13, 8, 8).to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
    weights, kernels = _to_float32((head[:, :4], head[:, 4:]))
    for value, part in ((weights, head[:, :4]), (kernels, head[:, 4:])):
        assert value.dtype == torch.float32 and value.is_contiguous()
        assert torch.equal(value, part.float())
    kept = torch.zeros(2, 3)
    assert _to_float32({"a": [kept]})["a"][0] is kept  # float32 values pass through as they are


def test_the_network_input_dtype_follows_the_threads_form():
    method = seeded("wskpn:xs", 1)
    assert method.network_input_dtype() == torch.float32  # no form installed
    with run_networks_as(method, "channels_last+bf16"):
        assert method.network_input_dtype() == torch.bfloat16
        seen = []
        other = threading.Thread(target=lambda: seen.append(method.network_input_dtype()))
        other.start()
        other.join()
        assert seen == [torch.float32]  # another thread runs its own form (none here)
    for form in ("channels_last", "compile+bf16", "compile-step+bf16"):
        with run_networks_as(method, form):
            assert method.network_input_dtype() == torch.float32


@needs_bf16
def test_a_fused_step_in_bf16_gives_what_it_gave_with_float32_network_input():
    """The native pass writes the fused network's input in bfloat16 under a bf16 form: the same values autocast's
    cast would make, so the same outputs."""
    import model.methods.fused as fused

    method = build_method("fused:fast", 1).eval().for_inference()
    batches = frames(24)
    original = method.network_input_dtype
    dtypes = []
    native_pass = fused.fused_features_x1
    fused.fused_features_x1 = lambda *a, **k: dtypes.append(a[-1]) or native_pass(*a, **k)
    with run_networks_as(method, "channels_last+bf16"):
        assert method.network_input_dtype() == torch.bfloat16
        given = stream(method, batches)
        object.__setattr__(method, "network_input_dtype", lambda: torch.float32)
        try:
            expected = stream(method, batches)
        finally:
            object.__setattr__(method, "network_input_dtype", original)
            fused.fused_features_x1 = native_pass
    assert dtypes == [torch.bfloat16] * len(batches) + [torch.float32] * len(batches)
    for a, b in zip(given, expected):
        assert torch.equal(a, b)
