"""The tests' shared builders: tiny, seeded data with known answers, as plain functions (no fixtures).

Every test that needs a tensor, a frame, a sequence on disk, a tiny dataset, a test method, a shipped model or an
HTTP error body builds it here, so there is one copy of each. Randomness always comes from an explicit seed.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import io
import socket
from pathlib import Path

import numpy as np
import OpenEXR
import torch
import torch.nn.functional as F
from torch import nn

from model.training.checkpoint import save_checkpoint
from model.io.dataset import Dataset, SequenceWriter
from model.io.frames import FrameBundle, box_downsample
from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.registry import build_method
from model.deployment.pretrained import ship_checkpoint

GRADIENT_SIZE = 16  # gradient_frame's side (render resolution)
GRADIENT_FRAMES = 4  # frames per sequence of write_gradient_dataset


# --------------------------------------------------------------------------------------------------- tensors

def generator(seed: int = 0) -> torch.Generator:
    """A CPU generator seeded with ``seed``."""
    return torch.Generator().manual_seed(seed)


def rand(*shape, seed: int = 0, lo: float = 0.0, hi: float = 1.0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Uniform values in [lo, hi) of ``shape`` (float64 unless told), from ``seed``."""
    return lo + (hi - lo) * torch.rand(*shape, generator=generator(seed), dtype=dtype)


def noisy_constant(truth: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Unbiased non-negative noise: truth * 2U with U uniform in [0, 1) (relative standard deviation 0.58)."""
    return truth * 2.0 * torch.rand(truth.shape, generator=generator).to(truth.device)


def mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean())


# ------------------------------------------------------------------------------------- frame batches (torch)

def static_frame(batch: int = 1, size: int = 16, seed: int = 0, cut: bool | list[bool] = False,
                 jitter: tuple[float, float] = (0.0, 0.0), *, split: bool = False,
                 material: bool = False) -> FrameBatch:
    """A static scene (a flat wall facing a still camera, depth 2, albedo 0.5, no motion): history maps pixel to
    pixel and always passes the geometry test, so accumulation really happens and camera cuts are observable.
    Only the noisy color changes with the seed: uniform in [0, 2), or with ``split`` diffuse (uniform in [0, 1))
    plus specular (uniform in [0, 0.3)) with both buffers set. ``material`` adds specular albedo 0.04 and
    roughness 0.5."""
    g = generator(seed)
    normal = torch.zeros(batch, 3, size, size)
    normal[:, 2] = 1.0
    cuts = torch.tensor(cut if isinstance(cut, list) else [cut] * batch, dtype=torch.bool)
    extra = {}
    if split:
        diffuse = torch.rand(batch, 3, size, size, generator=g)
        specular = torch.rand(batch, 3, size, size, generator=g) * 0.3
        color = diffuse + specular
        extra.update(diffuse=diffuse, specular=specular)
    else:
        color = torch.rand(batch, 3, size, size, generator=g) * 2
    if material:
        extra.update(specular_albedo=torch.full((batch, 3, size, size), 0.04),
                     roughness=torch.full((batch, 1, size, size), 0.5))
    return FrameBatch(color=color, albedo=torch.full((batch, 3, size, size), 0.5), normal=normal,
                      depth=torch.full((batch, 1, size, size), 2.0), motion=torch.zeros(batch, 2, size, size),
                      jitter=torch.tensor([jitter] * batch), camera_cut=cuts, **extra)


def plane_frame(color: torch.Tensor, depth: torch.Tensor | None = None, albedo: float = 0.5,
                motion: tuple[float, float] = (0.0, 0.0), jitter: tuple[float, float] = (0.0, 0.0),
                camera_cut: list[bool] | None = None) -> FrameBatch:
    """A frame of a surface facing the camera (normal +z), depth 1 unless given, uniform motion and jitter."""
    n, _, h, w = color.shape
    normal = torch.zeros(n, 3, h, w, dtype=color.dtype, device=color.device)
    normal[:, 2] = 1.0
    if depth is None:
        depth = torch.ones(n, 1, h, w, dtype=color.dtype, device=color.device)
    motion_field = torch.tensor(motion, dtype=color.dtype, device=color.device).view(1, 2, 1, 1).expand(n, 2, h, w)
    cut = torch.tensor(camera_cut if camera_cut is not None else [False] * n, device=color.device)
    return FrameBatch(color=color, albedo=torch.full_like(color, albedo), normal=normal, depth=depth,
                      motion=motion_field.contiguous(), jitter=torch.tensor([jitter] * n, device=color.device),
                      camera_cut=cut)


def sample(frame: FrameBatch, i: int) -> FrameBatch:
    return FrameBatch(**{name: t[i : i + 1] for name, t in frame.tensors().items()})


# ----------------------------------------------------------------------------------- frame bundles (NumPy)

def make_frame(
    seed: int = 0,
    height: int = 4,
    width: int = 6,
    *,
    scales: tuple[int, ...] = (1, 2),
    split: bool = True,
    frame_index: int = 3,
    albedo_references: bool = False,
) -> FrameBundle:
    """A tiny valid frame: random buffers honouring every convention, one background pixel at (0, 0).

    diffuse + specular == color exactly, normals are unit length where depth > 0, and the scale-1
    reference is the 2x2 mean of the scale-2 one. ``albedo_references`` adds reference albedos and
    specular albedos at every reference scale, box-downsampled the same way.
    """
    rng = np.random.default_rng(seed)
    f32 = np.float32
    diffuse = rng.uniform(0, 4, (height, width, 3)).astype(f32)
    specular = rng.uniform(0, 2, (height, width, 3)).astype(f32)
    normal = rng.normal(size=(height, width, 3))
    normal = (normal / np.linalg.norm(normal, axis=2, keepdims=True)).astype(f32)
    depth = rng.uniform(0.5, 20, (height, width)).astype(f32)
    depth[0, 0] = 0.0  # the background: nothing hit, zero normal
    normal[0, 0] = 0.0
    top = max(scales, default=1)
    finest = rng.uniform(0, 5, (height * top, width * top, 3)).astype(f32)
    def pyramid(finest: np.ndarray) -> dict[int, np.ndarray]:
        return {scale: box_downsample(finest, top // scale) if scale < top else finest for scale in scales}

    references = pyramid(finest)
    target_shape = (height * top, width * top, 3)
    reference_albedos = pyramid(rng.uniform(0, 1, target_shape).astype(f32)) if albedo_references else {}
    reference_specular_albedos = pyramid(rng.uniform(0, 1, target_shape).astype(f32)) if albedo_references else {}
    return FrameBundle(
        color=diffuse + specular,
        albedo=rng.uniform(0, 1, (height, width, 3)).astype(f32),
        normal=normal,
        depth=depth,
        motion=rng.uniform(-3, 3, (height, width, 2)).astype(f32),
        jitter=(float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5))),
        frame_index=frame_index,
        sequence="tiny",
        camera_cut=True,
        diffuse=diffuse if split else None,
        specular=specular if split else None,
        specular_albedo=rng.uniform(0, 1, (height, width, 3)).astype(f32),
        roughness=rng.uniform(0, 1, (height, width)).astype(f32),
        references=references,
        reference_albedos=reference_albedos,
        reference_specular_albedos=reference_specular_albedos,
    )


def uncut_frame(seed: int, index: int, scales: tuple[int, ...] = (1, 2)) -> FrameBundle:
    """``make_frame`` without its camera cut (history continues across such frames)."""
    return dataclasses.replace(make_frame(seed, frame_index=index, scales=scales), camera_cut=False)


def synthetic_frame(rng: np.random.Generator, index: int, width: int, height: int, camera_cut: bool = False,
                    scales: tuple[int, ...] = (1, 2)) -> FrameBundle:
    """A valid random frame: a smooth reference, noisy color around it, random geometry and a small motion."""
    top = max(scales)
    ys, xs = np.mgrid[0:height * top, 0:width * top].astype(np.float32) / top
    phase = rng.uniform(0, 6, size=3).astype(np.float32)
    reference_top = np.stack([0.5 + 0.4 * np.sin(0.3 * xs + 0.2 * ys + p) for p in phase], axis=2)
    references = {top: reference_top.astype(np.float32)}
    for scale in scales:
        references[scale] = box_downsample(reference_top, top // scale) if scale != top else references[top]
    noise = rng.exponential(1.0, size=(height, width, 3)).astype(np.float32)
    color = references[1] * noise if 1 in references else box_downsample(reference_top, top) * noise
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    diffuse = (color * rng.uniform(0.2, 0.8, size=color.shape)).astype(np.float32)
    return FrameBundle(
        color=color, albedo=rng.uniform(0, 1, size=(height, width, 3)).astype(np.float32), normal=normal,
        depth=rng.uniform(1, 5, size=(height, width)).astype(np.float32),
        motion=rng.uniform(-1, 1, size=(height, width, 2)).astype(np.float32),
        jitter=tuple(float(v) for v in rng.uniform(-0.5, 0.5, size=2)), frame_index=index, camera_cut=camera_cut,
        diffuse=diffuse, specular=color - diffuse,
        references={scale: references[scale] for scale in scales})


def gradient_frame(index: int, seed: int, scales: tuple[int, ...], camera_cut: bool = False) -> FrameBundle:
    """A smooth moving gradient as reference; the noisy color is the scale-1 reference plus seeded noise."""
    rng = np.random.default_rng(seed * 100 + index)
    fine = 2 * GRADIENT_SIZE
    y, x = np.mgrid[0:fine, 0:fine].astype(np.float32) / fine
    base = np.stack([x + 0.05 * index, y, 0.5 * (x + y)], axis=2) * (0.5 + 0.2 * seed)
    reference2 = np.ascontiguousarray(base, dtype=np.float32)
    reference1 = box_downsample(reference2, 2)
    noise = rng.normal(0.0, 0.2, reference1.shape).astype(np.float32)
    references = {1: reference1, 2: reference2}
    return FrameBundle(
        color=np.clip(reference1 + noise, 0.0, None),
        albedo=np.full((GRADIENT_SIZE, GRADIENT_SIZE, 3), 0.5, np.float32),
        normal=np.broadcast_to(np.array([0, 0, 1], np.float32), (GRADIENT_SIZE, GRADIENT_SIZE, 3)).copy(),
        depth=np.ones((GRADIENT_SIZE, GRADIENT_SIZE), np.float32),
        motion=np.zeros((GRADIENT_SIZE, GRADIENT_SIZE, 2), np.float32),
        jitter=(0.0, 0.0), frame_index=index, camera_cut=camera_cut,
        references={s: references[s] for s in scales})


# ---------------------------------------------------------------------------------- sequences and datasets

def frame_sequence(count: int, *, height: int = 4, width: int = 6, scales=(1, 2), cuts=(0,), seed: int = 0):
    """``count`` frames of ``make_frame`` (seeds ``seed``, ``seed`` + 1, ...), camera cuts at ``cuts``."""
    for index in range(count):
        frame = make_frame(seed + index, height, width, scales=scales, frame_index=index)
        frame.sequence = ""
        frame.camera_cut = index in cuts
        yield frame


def write_frame_sequence(root: Path, name: str, count: int = 3, *, scene: str | None = None,
                         metadata: dict | None = None, **frame_options) -> Path:
    """The sequence folder ``root/name`` of ``frame_sequence(count, **frame_options)`` frames (a camera cut on
    frame 0 unless ``cuts`` says otherwise)."""
    with SequenceWriter(root / name, name, scene=scene, metadata=metadata) as writer:
        for frame in frame_sequence(count, **frame_options):
            writer.add(frame)
    return root / name


def write_sequence(root: Path, name: str, frames: int, size: tuple[int, int] = (16, 16), cuts: tuple[int, ...] = (),
                   seed: int = 0, scales: tuple[int, ...] = (1, 2)) -> Path:
    rng = np.random.default_rng(seed)
    width, height = size
    with SequenceWriter(root / name, name) as writer:
        for index in range(frames):
            writer.add(synthetic_frame(rng, index, width, height, camera_cut=index in cuts, scales=scales))
    return root / name


def write_tiny_dataset(root: Path, size: tuple[int, int] = (16, 16)) -> Path:
    """Two training sequences (one with a cut at frame 3) and one validation sequence, 16x16 by default."""
    dataset = Dataset.create(root)
    for name, split, frames, cuts, seed in (("alpha", "train", 6, (3,), 1), ("beta", "train", 5, (), 2),
                                            ("gamma", "validation", 3, (), 3)):
        write_sequence(root, name, frames, size, cuts, seed)
        dataset.add_sequence_dir(name, split)
    return root


def write_gradient_dataset(root: Path, scales: tuple[int, ...] = (1, 2), split: str = "test") -> Path:
    """Two sequences of 4 frames at 16x16; sequence 'b' has a camera cut before frame 2."""
    dataset = Dataset.create(root)
    for seed, name in enumerate(("a", "b")):
        with SequenceWriter(root / name, name) as writer:
            for index in range(GRADIENT_FRAMES):
                writer.add(gradient_frame(index, seed, scales, camera_cut=(name == "b" and index == 2)))
        dataset.add_sequence_dir(name, split)
    return root


# ------------------------------------------------------------------------------------------------ methods

class NoisyInput(Method):
    """The noisy color, nearest-upscaled to the output scale; records what each step saw."""

    name = "noisy_input"

    def __init__(self, preset: str = "default", scale: int = 1):
        super().__init__(preset, scale)
        self.seen: list[dict] = []

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        self.seen.append({"history": None if state is None else int(state["count"].max()),
                          "cut": bool(frame.camera_cut[0]), "reference": frame.reference is not None})
        count = torch.ones(frame.batch_size, 1, 1, 1) if state is None else state["count"] + 1
        output = frame.color.repeat_interleave(self.scale, dim=2).repeat_interleave(self.scale, dim=3)
        return output, {"count": count}


def randomize_batch_norms(module: nn.Module, seed: int = 1) -> None:
    """Give every BatchNorm non-trivial affine parameters and running statistics, as after training."""
    g = torch.Generator().manual_seed(seed)
    for bn in module.modules():
        if isinstance(bn, nn.BatchNorm2d):
            c = bn.num_features
            with torch.no_grad():
                bn.weight.copy_(torch.rand(c, generator=g) * 1.5 + 0.25)
                bn.bias.copy_(torch.randn(c, generator=g) * 0.5)
                bn.running_mean.copy_(torch.randn(c, generator=g) * 0.5)
                bn.running_var.copy_(torch.rand(c, generator=g) * 2.0 + 0.1)


# -------------------------------------------------------------------------------------- files and models

def load_script(name: str, folder: str = "scripts"):
    """A module of ``scripts/`` (or of another top-level folder of files, such as ``experiments/``) by its file
    name without ``.py`` (these folders hold files, not packages)."""
    path = Path(__file__).resolve().parents[1] / folder / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def zero_bomb(width: int, height: int) -> bytes:
    """An all-zero ZIP-compressed EXR declaring width x height: a few kilobytes that decode to megabytes."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    stream = io.BytesIO()
    OpenEXR.File(header, {"color": np.zeros((height, width, 3), np.float32)}).write(stream)
    return stream.getvalue()


def aov_bomb(width: int, height: int, channels: int = 127) -> bytes:
    """An all-zero ZIP-compressed EXR of ``channels`` float channels aov000.Y, ... that no layout reads: at
    2048x1024 and 127 channels, about 1 MB that decodes to 1.07 GB, within 128 values per pixel."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    planes = {f"aov{index:03d}.Y": np.zeros((height, width), np.float32) for index in range(channels)}
    stream = io.BytesIO()
    OpenEXR.File(header, planes).write(stream)
    return stream.getvalue()


def with_reference_part(body: bytes, scale: int) -> bytes:
    """A frame bundle EXR ``body`` with one more, all-zero reference part ``reference_x<scale>`` (R, G, B)."""
    parts = OpenEXR.File(io.BytesIO(body), separate_channels=True).parts
    low, high = parts[0].header["dataWindow"]
    width, height = (int(high[0]) - int(low[0]) + 1) * scale, (int(high[1]) - int(low[1]) + 1) * scale
    rebuilt = [OpenEXR.Part({key: value for key, value in part.header.items() if key != "channels"},
                            {name: channel.pixels for name, channel in part.channels.items()}, part.name())
               for part in parts]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "scale": scale,
              "displayWindow": parts[0].header["displayWindow"],
              "dataWindow": (np.array([0, 0], np.int32), np.array([width - 1, height - 1], np.int32))}
    zeros = {f"reference.{c}": np.zeros((height, width), np.float32) for c in "RGB"}
    rebuilt.append(OpenEXR.Part(header, zeros, f"reference_x{scale}"))
    stream = io.BytesIO()
    OpenEXR.File(rebuilt).write(stream)
    return stream.getvalue()


def ship_tiny(root, name="wskpn-xs-x1", report=None, **options):
    """A seeded wskpn:xs checkpoint (with optimizer state, as training writes it) shipped under ``root``."""
    torch.manual_seed(3)
    method = build_method("wskpn:xs", 1)
    optimizer = torch.optim.Adam(method.parameters())
    checkpoint = save_checkpoint(root.parent / f"{name}-source.pt", method=method, optimizer=optimizer, step=120,
                                 train_config={"steps": 150, "seed": 7, "data": "data/demo"},
                                 best_metric={"name": "validation/psnr", "value": 25.0, "step": 100})
    return ship_checkpoint(checkpoint, name, root=root, report=report, report_source="runs/x/best.pt", **options)


def report_for(source="runs/x/best.pt", scale=1):
    def row(label, method, preset, psnr, source_=None):
        return {"label": label, "source": source_ or label, "method": method, "preset": preset, "scale": scale,
                "metrics": {"psnr": psnr, "flip": 0.1}, "ms_per_frame": 5.0, "time_ratio_to_oidn": 0.5}

    return {"split": "test", "scale": scale, "sequences": [{"name": "moving_light_s4", "frames": 16},
                                                           {"name": "glass_s4", "frames": 16}],
            "methods": [row("wskpn:xs", "wskpn", "xs", 30.5, source), row("oidn:high", "oidn", "high", 31.0),
                        row("oidn-taa:high", "oidn-taa", "high", 31.4), row("svgf", "svgf", "default", 27.0)]}


# --------------------------------------------------------------------------------------------------- HTTP

def closed_port() -> int:
    """A local TCP port nothing listens on (bound once, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def error_of(response, status: int, code: str | None = None) -> dict:
    """The error body of a response, after checking its status (and, when given, its code)."""
    assert response.status_code == status, response.text
    body = response.json()["error"]
    if code is not None:
        assert body["code"] == code, body
    return body


def error_message(response, status: int, code: str) -> str:
    """``error_of``'s message."""
    return error_of(response, status, code)["message"]


def blurring_oidn(frame, quality):
    """A deterministic stand-in for OIDN: a 3 x 3 box blur of the colour (OIDN's own output is not held here)."""
    return F.avg_pool2d(frame.color, 3, stride=1, padding=1, count_include_pad=False)


def coherent_frame(frame: FrameBatch) -> FrameBatch:
    """The frame with one smooth surface (the synthetic frames draw their normals anew each frame, which fails every
    geometry test) and a sub-pixel motion, so the history, the means and their warps all take part."""
    height, width = frame.depth.shape[-2:]
    normal = torch.zeros_like(frame.normal)
    normal[:, 2] = 1.0
    depth = 1.0 + torch.linspace(0.0, 0.2, width).expand(1, 1, height, width).clone()
    motion = torch.tensor([-0.6, -0.3]).view(1, 2, 1, 1).expand_as(frame.motion).clone()
    motion[..., :, width // 2:] = 0.25  # half the frame moves another way: reads at other sub-pixel offsets
    return dataclasses.replace(frame, normal=normal, depth=depth, motion=motion)
