"""scripts/bench_int8.py: one tiny same-run comparison of float32 and int8 JNDS, and its network-share bound."""

from __future__ import annotations

import json

import pytest

from tests.builders import load_script

bench = load_script("bench_int8")


def test_a_tiny_run_times_both_forms_and_bounds_the_speed_up_by_the_network_share(tmp_path, capsys):
    out = tmp_path / "int8.json"
    bench.main(["--sizes", "16", "--frames", "2", "--warmup", "1", "--json", str(out)])
    (result,) = json.loads(out.read_text())["results"]
    assert (result["render"], result["output"], result["threads"]) == (16, 32, 1)
    forms = result["forms"]
    assert list(forms) == ["fp32", "int8 eager"]
    for form in forms.values():
        assert 0 < form["network_ms"] < form["ms"]
    assert forms["fp32"]["speedup"] == 1.0
    assert forms["int8 eager"]["speedup"] == pytest.approx(forms["fp32"]["ms"] / forms["int8 eager"]["ms"])
    assert forms["fp32"]["display_psnr_vs_fp32"] == 100.0 > forms["int8 eager"]["display_psnr_vs_fp32"] > 20
    share = result["network_share"]
    assert share == pytest.approx(forms["fp32"]["network_ms"] / forms["fp32"]["ms"])
    assert result["bound_if_network_free"] == pytest.approx(1 / (1 - share))
    assert "int8 of the network alone is at most" in capsys.readouterr().out


def test_shipped_refuses_other_weights():
    with pytest.raises(SystemExit):
        bench.main(["--shipped", "--preset", "m"])
