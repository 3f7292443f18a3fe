"""Int8 quantization of a convolutional network: quantization-aware training (QAT) and a real int8 CPU path.

PyTorch's eager-mode quantization (``torch.ao.quantization``, ``x86`` backend). A network that wants it wraps its
quantized region in ``QuantStub`` / ``DeQuantStub``, uses one ``FloatFunctional`` per concatenation and writes
convolutions followed by ReLUs as ``conv_relu`` pairs; ``prepare_qat`` then fuses the pairs and swaps in
fake-quantized modules, and ``convert_to_int8`` swaps those for real int8 ones. Weights are per output channel and
symmetric, activations per tensor and affine, in 7 bits (``reduce_range``: without VNNI, full 8-bit activations
can overflow the int16 sums of the u8 x s8 GEMMs). Eager mode rather than PT2E: PT2E graphs are fast only once
``torch.compile`` lowers them, while eager mode gives int8 convolutions at once for any frame size. Submodules with
``qconfig`` None stay float32 (JNDS's kernel-weight heads). The scheme and these choices in detail:
docs/methods.md, "model.methods.quantization".
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from contextlib import contextmanager

import torch
import torch.ao.nn.quantized as nnq
import torch.ao.quantization as tq
from torch import nn

__all__ = [
    "QUANTIZATION_BACKEND",
    "conv_relu",
    "fuse_conv_relu",
    "prepare_qat",
    "convert_to_int8",
    "is_calibrated",
    "set_observers",
    "has_fake_quantization",
    "is_int8",
    "quiet_quantization_warnings",
]

QUANTIZATION_BACKEND = "x86"
"""torch's x86 quantized engine: picks fbgemm or oneDNN kernels per convolution shape."""


@contextmanager
def quiet_quantization_warnings() -> Iterator[None]:
    """Silence torch.ao's deprecation notices (and its reduce_range / quantized-tensor notes) inside the block."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"torch\.ao\.quantization is deprecated")
        warnings.filterwarnings("ignore", message=r".*reduce_range will be deprecated")
        warnings.filterwarnings("ignore", message=r"torch\.quantize_per_tensor, torch\.quantize_per_channel")
        yield


def conv_relu(in_channels: int, out_channels: int, kernel_size: int) -> nn.Sequential:
    """A same-size convolution followed by a ReLU, as the pair ``fuse_conv_relu`` fuses into one int8 op.

    Parameter names stay ``<name>.0.weight`` / ``.0.bias`` through fusion and QAT preparation, so a float32
    state dict loads into the QAT model (strict=False leaves only the observers' buffers unset).
    """
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2), nn.ReLU())


def _conv_relu_pairs(module: nn.Module) -> list[list[str]]:
    return [
        [f"{name}.0", f"{name}.1"]
        for name, child in module.named_modules()
        if isinstance(child, nn.Sequential) and len(child) == 2
        and type(child[0]) is nn.Conv2d and type(child[1]) is nn.ReLU
    ]


def fuse_conv_relu(module: nn.Module) -> nn.Module:
    """Fuse every ``conv_relu`` pair inside ``module`` (in place, QAT flavour); returns ``module``."""
    pairs = _conv_relu_pairs(module)
    if pairs:
        with quiet_quantization_warnings():
            tq.fuse_modules_qat(module, pairs, inplace=True)
    return module


def prepare_qat(module: nn.Module, backend: str = QUANTIZATION_BACKEND) -> nn.Module:
    """Fuse conv + ReLU pairs and insert fake quantization (in place); returns ``module`` in training mode.

    Every submodule is quantized except those whose ``qconfig`` attribute is already set to None.
    """
    float_children = [child for child in module.modules() if getattr(child, "qconfig", "unset") is None]
    module.train()
    with quiet_quantization_warnings():
        qconfig = tq.get_default_qat_qconfig(backend)
        module.qconfig = qconfig
        for child in float_children:
            child.qconfig = None
        fuse_conv_relu(module)
        tq.prepare_qat(module, inplace=True)
    return module


def set_observers(module: nn.Module, enabled: bool) -> None:
    """Let the fake quantizers' observers update their ranges (training) or freeze them (evaluation)."""
    module.apply(tq.enable_observer if enabled else tq.disable_observer)


def _fake_quantizers(module: nn.Module) -> list[tq.FakeQuantizeBase]:
    return [child for child in module.modules() if isinstance(child, tq.FakeQuantizeBase)]


def has_fake_quantization(module: nn.Module) -> bool:
    return bool(_fake_quantizers(module))


def is_calibrated(module: nn.Module) -> bool:
    """True when every activation quantizer has seen data (its observed range is finite)."""
    quantizers = _fake_quantizers(module)
    if not quantizers:
        return False
    for quantizer in quantizers:
        observer = getattr(quantizer, "activation_post_process", None)
        min_val = getattr(observer, "min_val", None)
        if min_val is None or min_val.numel() == 0 or not torch.isfinite(min_val).all():
            return False
    return True


def is_int8(module: nn.Module) -> bool:
    """True once ``convert_to_int8`` has replaced the fake-quantized modules by int8 ones."""
    # Conversion turns every QuantStub into a Quantize module: the entry to the int8 region.
    return any(isinstance(child, nnq.Quantize) for child in module.modules())


def convert_to_int8(module: nn.Module, backend: str = QUANTIZATION_BACKEND) -> nn.Module:
    """Replace fake-quantized modules by int8 ones (in place, eval mode); returns ``module``.

    Needs a QAT-prepared module on the CPU whose observers have seen data; selects ``backend`` as torch's
    quantized engine (a process-wide setting) so the int8 kernels run with the scheme QAT simulated.
    """
    if not has_fake_quantization(module):
        raise ValueError("convert_to_int8 needs a module prepared with prepare_qat")
    if not is_calibrated(module):
        raise ValueError("the quantized model has not seen any data yet (its activation ranges are unset): "
                         "train it (QAT) or run a few frames in training mode before converting")
    devices = {p.device.type for p in module.parameters()} | {b.device.type for b in module.buffers()}
    if devices != {"cpu"}:
        raise ValueError(f"int8 kernels run on the CPU only; the module is on {sorted(devices)}")
    if backend not in torch.backends.quantized.supported_engines:
        raise RuntimeError(f"quantized engine {backend!r} is not available in this torch build "
                           f"(supported: {torch.backends.quantized.supported_engines})")
    torch.backends.quantized.engine = backend
    module.eval()
    with quiet_quantization_warnings():
        tq.convert(module, inplace=True)
    return module
