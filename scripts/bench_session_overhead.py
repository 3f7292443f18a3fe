"""What a session costs over HTTP: per-frame round trip of POST /sessions/{id}/frames against method.step in process.

    .venv/bin/python scripts/bench_session_overhead.py                          # jnds:xs, 128x128 -> 256x256
    .venv/bin/python scripts/bench_session_overhead.py --method munet:xs --frames 60 --threads 1
    .venv/bin/python scripts/bench_session_overhead.py --checkpoint runs/jnds-s/last.pt --data data/seq_0
    .venv/bin/python scripts/bench_session_overhead.py --url http://gpu-box:8000 --model jnds-s-x2@champion \\
        --checkpoint jnds-s.pt --api-key "$DENOISER_API_KEY"

Without ``--url`` the API runs in this process (uvicorn on a free port, in a thread) on a temporary data folder
and MLflow store; the method (``--method`` preset with seeded random weights, or ``--checkpoint``) is saved,
registered there, and a session is opened on it by name. Timing does not depend on the weights. With ``--url``,
the model must already be registered on that server (``--model NAME``, ``NAME/VERSION`` or ``NAME@ALIAS``) and
``--checkpoint`` gives the same weights for the in-process side.

Frames are synthetic valid frame bundles (or the first sequence of ``--data``, cycled and renumbered), encoded to
EXR before timing. Timed per frame, after ``--warmup`` frames, median over ``--frames``:

- round trip: the client's POST until the whole output EXR has arrived (upload, server, download);
- server: the X-Server-Ms header (body read, EXR decode, step, Redis mirror, EXR encode);
- step: the X-Inference-Ms header (method.step in the session);
- in process: method.step on the same frames, here, with the same torch thread count, history carried;
  interleaved with the HTTP stream (frame i over HTTP, then frame i here), so load from other processes on a
  shared machine hits both alike.

The overhead ratio is round trip / in-process step. In-process mode shares one Python process (and its GIL)
between client and server, which a real deployment does not; ``--url`` measures a separate server.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.checkpoint import load_method, save_checkpoint  # noqa: E402
from model.exr import decode_image_exr, encode_frame_exr  # noqa: E402
from model.frames import FrameBundle  # noqa: E402
from model.methods.base import FrameBatch  # noqa: E402
from model.methods.registry import build_method  # noqa: E402


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="jnds:xs", help="NAME:PRESET to build (default jnds:xs)")
    parser.add_argument("--scale", type=int, default=2, help="output / render resolution (default 2)")
    parser.add_argument("--checkpoint", type=Path, help="a model.checkpoint file instead of --method")
    parser.add_argument("--model", help="already registered model: NAME, NAME/VERSION or NAME@ALIAS")
    parser.add_argument("--url", help="a running API (default: start one in this process)")
    parser.add_argument("--api-key", default=os.environ.get("DENOISER_API_KEY"), help="X-API-Key for --url")
    parser.add_argument("--redis-url", default=os.environ.get("DENOISER_REDIS_URL", "redis://127.0.0.1:6379/0"),
                        help="Redis of the in-process API (session mirror)")
    parser.add_argument("--data", type=Path, help="a sequence folder or dataset folder to take frames from")
    parser.add_argument("--size", type=int, default=128, help="render resolution of synthetic frames (square)")
    parser.add_argument("--frames", type=int, default=30, help="timed frames (default 30)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames first (default 5)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    return parser.parse_args()


# --- frames ----------------------------------------------------------------------------------------------


def synthetic_frames(count: int, size: int, seed: int = 0) -> list[FrameBundle]:
    """Valid frames of a smooth moving pattern: noisy color, random unit normals, depth, small motion."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    frames = []
    for index in range(count):
        clean = np.stack([0.5 + 0.4 * np.sin(0.05 * (xs + index) + 0.03 * ys + phase) for phase in (0, 2, 4)], 2)
        color = (clean * rng.exponential(1.0, size=clean.shape)).astype(np.float32)
        normal = rng.normal(size=(size, size, 3)).astype(np.float32)
        normal /= np.linalg.norm(normal, axis=2, keepdims=True)
        diffuse = (color * rng.uniform(0.2, 0.8, size=color.shape)).astype(np.float32)
        frames.append(FrameBundle(
            color=color, albedo=rng.uniform(0, 1, size=color.shape).astype(np.float32), normal=normal,
            depth=rng.uniform(1, 5, size=(size, size)).astype(np.float32),
            motion=np.full((size, size, 2), -1.0, np.float32),
            jitter=tuple(float(v) for v in rng.uniform(-0.5, 0.5, size=2)), frame_index=index,
            diffuse=diffuse, specular=color - diffuse))
    return frames


def dataset_frames(path: Path, count: int) -> list[FrameBundle]:
    """``count`` frames of the sequence at ``path`` (or a dataset's first sequence), cycled, renumbered 0..count-1."""
    from model.dataset import Dataset, DatasetError, Sequence

    try:
        sequence = Sequence(path)
    except DatasetError:  # not a sequence folder: a dataset folder
        sequence = Dataset(path).sequences()[0]
    source = list(sequence)
    frames = []
    for index in range(count):
        frame = source[index % len(source)]
        frame.frame_index, frame.camera_cut = index, False
        frames.append(frame)
    return frames


# --- the API ---------------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def start_local_api(work: Path, args: argparse.Namespace, checkpoint: Path) -> tuple[str, str, object]:
    """Register ``checkpoint`` in a fresh store under ``work`` and serve the API from a thread; (url, model, server)."""
    tracking_uri = f"sqlite:///{work / 'mlflow' / 'mlflow.db'}"
    os.environ.update({"DENOISER_DATA_DIR": str(work / "data"), "DENOISER_TRACKING_URI": tracking_uri,
                       "DENOISER_REDIS_URL": args.redis_url, "DENOISER_SESSION_THREADS": str(args.threads)})
    os.environ.pop("DENOISER_API_KEY", None)
    from service.settings import get_settings

    get_settings.cache_clear()
    model = args.model
    if model is None:
        from workers.tracking import MLflowTracker

        method = load_method(checkpoint)
        tracker = MLflowTracker(tracking_uri, experiment="bench")
        tracker.start({"method": method.label})
        model = f"bench-{method.name}-{method.preset}-x{method.scale}"
        tracker.log_model(checkpoint, model, {"method": method.name, "preset": method.preset,
                                              "scale": str(method.scale), "params": str(method.parameter_count())})
        tracker.finish("FINISHED")

    import uvicorn

    try:
        from service.main import create_app

        app = create_app()
    except ImportError as error:  # a router module of another resource is missing: serve sessions and models
        print(f"note: full app unavailable ({error}); serving /sessions and /models only")
        from fastapi import FastAPI

        from service.errors import install_error_handlers
        from service.routes import models as models_routes
        from service.routes import sessions as sessions_routes

        app = FastAPI()
        install_error_handlers(app)
        app.include_router(models_routes.router)
        app.include_router(sessions_routes.router)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise SystemExit("the in-process API did not start")
        time.sleep(0.05)
    return f"http://127.0.0.1:{port}", model, server


def session_body(model: str) -> dict:
    if "@" in model:
        name, alias = model.split("@", 1)
        return {"model": name, "alias": alias}
    if "/" in model:
        name, version = model.split("/", 1)
        return {"model": name, "version": version}
    return {"model": model}


# --- timing ----------------------------------------------------------------------------------------------


class InProcess:
    """The same method stepping through the same frames here, with its own history."""

    def __init__(self, checkpoint: Path) -> None:
        self.method = load_method(checkpoint).for_inference()
        self.state = None
        self.outputs: list[np.ndarray] = []

    def step(self, frame: FrameBundle) -> float:
        batch = FrameBatch.from_bundles([frame], scale=None)
        with torch.no_grad():
            started = time.perf_counter()
            output, self.state = self.method.step(batch, self.state)
            elapsed = (time.perf_counter() - started) * 1000
        self.outputs.append(output[0].permute(1, 2, 0).numpy().copy())
        return elapsed


def run(url: str, model: str, frames: list[FrameBundle], bodies: list[bytes], local: InProcess, warmup: int,
        api_key: str | None) -> dict:
    """Each frame over HTTP, then the same frame in process: interleaved, so load from other processes on a
    shared machine hits both alike."""
    import httpx

    headers = {"X-API-Key": api_key} if api_key else {}
    times: dict[str, list[float]] = {"round_trip": [], "server": [], "inference": [], "local": []}
    outputs = []
    with httpx.Client(base_url=url, headers=headers, timeout=120) as client:
        created = client.post("/sessions", json={**session_body(model), "on_gap": "reject"})
        if created.status_code != 201:
            raise SystemExit(f"POST /sessions: {created.status_code} {created.text}")
        session = created.json()
        frames_url = f"/sessions/{session['id']}/frames"
        try:
            for index, (frame, body) in enumerate(zip(frames, bodies)):
                started = time.perf_counter()
                response = client.post(frames_url, content=body, headers={"Content-Type": "image/x-exr"})
                elapsed = (time.perf_counter() - started) * 1000
                if response.status_code != 200:
                    raise SystemExit(f"frame {index}: {response.status_code} {response.text}")
                outputs.append(response.content)
                local_ms = local.step(frame)
                if index >= warmup:
                    times["round_trip"].append(elapsed)
                    times["server"].append(float(response.headers["X-Server-Ms"]))
                    times["inference"].append(float(response.headers["X-Inference-Ms"]))
                    times["local"].append(local_ms)
        finally:
            client.delete(f"/sessions/{session['id']}")
    return {"session": session, "times": times, "outputs": outputs, "bytes_out": len(outputs[-1])}


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    total = args.warmup + args.frames
    with tempfile.TemporaryDirectory(prefix="bench-session-") as folder:
        work = Path(folder)
        checkpoint = args.checkpoint
        if checkpoint is None:
            if args.url:
                raise SystemExit("--url needs --checkpoint (the registered model's weights) for the in-process side")
            torch.manual_seed(0)
            checkpoint = save_checkpoint(work / "checkpoint.pt", method=build_method(args.method, scale=args.scale))
        label = load_method(checkpoint).label
        frames = dataset_frames(args.data, total) if args.data else synthetic_frames(total, args.size)
        bodies = [encode_frame_exr(frame) for frame in frames]

        server = None
        if args.url:
            if not args.model:
                raise SystemExit("--url needs --model: a model registered on that server")
            url, model = args.url.rstrip("/"), args.model
        else:
            url, model, server = start_local_api(work, args, checkpoint)
        local = InProcess(checkpoint)
        try:
            http = run(url, model, frames, bodies, local, args.warmup, args.api_key)
        finally:
            if server is not None:
                server.should_exit = True

    scale = http["session"]["model"]["scale"]
    height, width = frames[0].height, frames[0].width
    difference = max(float(np.abs(decode_image_exr(data) - expected).max())
                     for data, expected in zip(http["outputs"], local.outputs))
    median = statistics.median
    times = http["times"]
    round_trip, local_ms = median(times["round_trip"]), median(times["local"])
    print(f"{label} ({model}) {width}x{height} -> {width * scale}x{height * scale}, {args.frames} timed frames "
          f"after {args.warmup}, {args.threads} torch thread(s), frame EXR {len(bodies[0]) / 1e6:.2f} MB in, "
          f"{http['bytes_out'] / 1e6:.2f} MB out, {'server ' + url if args.url else 'API in this process'}")
    print(f"  HTTP round trip     median {round_trip:8.2f} ms/frame")
    print(f"    server (X-Server-Ms)     {median(times['server']):8.2f} ms   "
          f"step in session (X-Inference-Ms) {median(times['inference']):8.2f} ms")
    print(f"  in-process step     median {local_ms:8.2f} ms/frame")
    print(f"  overhead ratio (round trip / in-process step) {round_trip / local_ms:.2f}x, "
          f"+{round_trip - local_ms:.2f} ms/frame")
    print(f"  max |session output - in-process output| over the stream: {difference:.3g}")


if __name__ == "__main__":
    main()
