"""The native kernels' build: compiled once per source into the cache, refused clearly, and never half-loaded."""

import pytest
import torch

from model.ops import native


def test_builds_once_into_the_cache(tmp_path):
    first = native.build("reproject", tmp_path)
    stamp = first.stat().st_mtime_ns
    assert native.build("reproject", tmp_path) == first and first.stat().st_mtime_ns == stamp
    assert [p.name for p in tmp_path.iterdir()] == [first.name]  # no partial files left behind


def test_a_missing_compiler_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    with pytest.raises((RuntimeError, OSError)):
        native.build("reproject", tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_usable_only_without_gradients_on_float32_cpu_tensors():
    x = torch.zeros(1, 1, 4, 4)
    assert native.usable("reproject", x)
    assert not native.usable("reproject", x.double())
    with torch.enable_grad():
        assert not native.usable("reproject", x)
    with native.disabled():
        assert not native.usable("reproject", x)
    assert native.usable("reproject", x)



def test_configure_sets_the_switch_and_the_cache(tmp_path):
    try:
        native.configure(False, tmp_path / "kernels")
        assert not native.enabled() and not native.usable("reproject", torch.zeros(1))
        assert native._cache_dir() == tmp_path / "kernels"
    finally:
        native.configure(True, None)
    assert native.enabled() and native._cache_dir().name == "native"


def test_a_kernel_that_cannot_allocate_raises_memory_error_and_writes_nothing():
    """Scratch memory past any address space: the kernel refuses before touching a pixel (no crash, no output)."""
    huge = 2 ** 50  # a row this wide needs more scratch bytes than a 64-bit process can address
    out = torch.full((4,), 7.0)
    plane = torch.zeros(4)
    with pytest.raises(MemoryError, match="tail_x1"):
        native.call("tail", "tail_x1", 1, huge, plane, plane, plane, plane, plane, None, None, None, 2.0, out, out,
                    None)
    assert torch.equal(out, torch.full((4,), 7.0))
