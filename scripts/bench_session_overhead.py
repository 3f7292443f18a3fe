"""What a session costs over HTTP: per-frame round trip of POST /sessions/{id}/frames against method.step in process.

    .venv/bin/python scripts/bench_session_overhead.py                          # jnds:xs, 128x128 -> 256x256
    .venv/bin/python scripts/bench_session_overhead.py --method munet:xs --frames 60 --threads 1
    .venv/bin/python scripts/bench_session_overhead.py --checkpoint runs/jnds-s/last.pt --data data/seq_0
    .venv/bin/python scripts/bench_session_overhead.py --url http://gpu-box:8000 --model jnds-s-x2@champion \\
        --checkpoint jnds-s.pt --api-key "$DENOISER_API_KEY"

Without ``--url`` the API is started here on a free port, on a temporary data folder and MLflow store: by default
as its own process (``uvicorn service.main:app``), as in a deployment, so client and server share no Python
interpreter; ``--server thread`` runs it in a thread of this process instead (client and server then share one
GIL, which inflates the round trip). The method (``--method`` preset with seeded random weights, or
``--checkpoint``) is saved, registered there, and a session is opened on it by name. Timing does not depend on the
weights. With ``--url``, the model must already be registered on that server (``--model NAME``, ``NAME/VERSION``
or ``NAME@ALIAS``) and ``--checkpoint`` gives the same weights for the in-process side.

Frames are synthetic valid frame bundles (or the first sequence of ``--data``, cycled and renumbered). The client
is service.client.DenoiserClient. Timed per frame, after ``--warmup`` frames, median over ``--frames``:

- client encode: the frame bundle to EXR bytes (service.client.frame_bytes, ``--compression``);
- round trip: send_frame_raw's POST until the whole output EXR has arrived (upload, server, download);
- server: the X-Server-Ms header (body read, EXR decode, step, EXR encode; the Redis mirror is written in the
  background);
- step: the X-Inference-Ms header (method.step in the session);
- in process: method.step on the same frames, here, with the same torch thread count, history carried.

The two run in alternating blocks, ``--rounds`` times (HTTP stream, in-process stream, HTTP stream, ...; a new
session and a new history each round), and each median is over every timed frame of its blocks: blocks, not
frame-by-frame interleaving, because the server's work after answering a frame (its Redis mirror write) would
otherwise run beside the in-process step on a 2-core machine and slow it, while a client stepping nothing at that
moment does not feel it. Alternating still spreads slow drifts of other load over both sides.

The overhead ratio is round trip / in-process step; client encode is reported beside it, not in it. Round trip /
step in session is printed too (the same step, timed inside the server).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.checkpoint import load_method, save_checkpoint  # noqa: E402
from model.exr import decode_image_exr  # noqa: E402
from model.frames import FrameBundle  # noqa: E402
from model.methods.base import FrameBatch  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from service.client import FRAME_COMPRESSIONS, DenoiserClient, frame_bytes  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="jnds:xs", help="NAME:PRESET to build (default jnds:xs)")
    parser.add_argument("--scale", type=int, default=2, help="output / render resolution (default 2)")
    parser.add_argument("--checkpoint", type=Path, help="a model.checkpoint file instead of --method")
    parser.add_argument("--model", help="already registered model: NAME, NAME/VERSION or NAME@ALIAS")
    parser.add_argument("--url", help="a running API (default: start one here, see --server)")
    parser.add_argument("--server", choices=("process", "thread"), default="process",
                        help="without --url: run the API as its own uvicorn process (default) or in a thread here")
    parser.add_argument("--compression", choices=sorted(FRAME_COMPRESSIONS), default=None,
                        help="EXR compression of the frames sent (default: the client's, "
                             "service.client.FRAME_COMPRESSION)")
    parser.add_argument("--api-key", default=os.environ.get("DENOISER_API_KEY"), help="X-API-Key for --url")
    parser.add_argument("--redis-url", default=os.environ.get("DENOISER_REDIS_URL", "redis://127.0.0.1:6379/0"),
                        help="Redis of the in-process API (session mirror)")
    parser.add_argument("--data", type=Path, help="a sequence folder or dataset folder to take frames from")
    parser.add_argument("--size", type=int, default=128, help="render resolution of synthetic frames (square)")
    parser.add_argument("--frames", type=int, default=30, help="timed frames (default 30)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames first (default 5)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternating HTTP / in-process blocks of the whole stream (default 3)")
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
    # Copies: cycling repeats a source frame, and each repeat has its own index.
    return [dataclasses.replace(source[index % len(source)], frame_index=index, camera_cut=False)
            for index in range(count)]


# --- the API ---------------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def register_checkpoint(work: Path, args: argparse.Namespace, checkpoint: Path) -> tuple[dict, str]:
    """Register ``checkpoint`` in a fresh store under ``work``; (the API's DENOISER_* settings, the model name)."""
    tracking_uri = f"sqlite:///{work / 'mlflow' / 'mlflow.db'}"
    env = {"DENOISER_DATA_DIR": str(work / "data"), "DENOISER_TRACKING_URI": tracking_uri,
           "DENOISER_REDIS_URL": args.redis_url, "DENOISER_SESSION_THREADS": str(args.threads)}
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
    return env, model


def wait_until_up(url: str, alive, what: str) -> None:
    import httpx

    deadline = time.monotonic() + 120
    while True:
        try:
            if httpx.get(f"{url}/health", timeout=1).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if not alive() or time.monotonic() > deadline:
            raise SystemExit(f"{what} did not start")
        time.sleep(0.1)


class ProcessApi:
    """``uvicorn service.main:app`` as a child process (the deployment's program), stopped on ``stop()``."""

    def __init__(self, env: dict) -> None:
        port = free_port()
        environment = {**os.environ, **env}
        environment.pop("DENOISER_API_KEY", None)
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), environment.get("PYTHONPATH")]))
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.main:app", "--host", "127.0.0.1", "--port", str(port),
             "--log-level", "warning", "--no-access-log"], cwd=REPO, env=environment)
        self.url = f"http://127.0.0.1:{port}"
        try:
            wait_until_up(self.url, lambda: self.process.poll() is None, "the API process")
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


class ThreadApi:
    """The API served from a thread of this process (client and server share the GIL)."""

    def __init__(self, env: dict) -> None:
        import uvicorn

        os.environ.update(env)
        os.environ.pop("DENOISER_API_KEY", None)
        from service.settings import get_settings

        get_settings.cache_clear()
        from service.main import create_app

        port = free_port()
        self.server = uvicorn.Server(uvicorn.Config(create_app(), host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=self.server.run, daemon=True)
        thread.start()
        self.url = f"http://127.0.0.1:{port}"
        wait_until_up(self.url, thread.is_alive, "the in-process API")

    def stop(self) -> None:
        self.server.should_exit = True


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
    """The same method stepping through the same frames here, a new history per stream."""

    def __init__(self, checkpoint: Path) -> None:
        self.method = load_method(checkpoint).for_inference()

    def stream(self, frames: list[FrameBundle]) -> tuple[list[np.ndarray], list[float]]:
        state, outputs, times = None, [], []
        for frame in frames:
            batch = FrameBatch.from_bundles([frame], scale=None)
            with torch.no_grad():
                started = time.perf_counter()
                output, state = self.method.step(batch, state)
                times.append((time.perf_counter() - started) * 1000)
            outputs.append(output[0].permute(1, 2, 0).numpy().copy())
        return outputs, times


def http_stream(client: DenoiserClient, model: str, frames: list[FrameBundle], compression: str | None) -> dict:
    """Each frame encoded and sent over HTTP in a new session: outputs and per-frame times."""
    times: dict[str, list[float]] = {"encode": [], "round_trip": [], "server": [], "inference": []}
    outputs, sizes = [], []
    options = {} if compression is None else {"compression": compression}
    session = client.create_session(**session_body(model), on_gap="reject")
    try:
        for frame in frames:
            started = time.perf_counter()
            body = frame_bytes(frame, **options)
            times["encode"].append((time.perf_counter() - started) * 1000)
            data, info = client.send_frame_raw(session["id"], body)
            outputs.append(data)
            sizes.append(len(body))
            times["round_trip"].append(info.round_trip_ms)
            times["server"].append(info.server_ms)
            times["inference"].append(info.inference_ms)
    finally:
        client.delete_session(session["id"])
    return {"session": session, "times": times, "outputs": outputs, "bytes_in": sizes[-1],
            "bytes_out": len(outputs[-1])}


def run(url: str, model: str, frames: list[FrameBundle], local: InProcess, warmup: int, rounds: int,
        api_key: str | None, compression: str | None) -> dict:
    """``rounds`` x (the stream over HTTP, then in process); times of frames after ``warmup`` in each stream."""
    times: dict[str, list[float]] = {"encode": [], "round_trip": [], "server": [], "inference": [], "local": []}
    difference = 0.0
    with DenoiserClient(url, api_key=api_key, timeout=120) as client:
        for _ in range(rounds):
            http = http_stream(client, model, frames, compression)
            expected, local_times = local.stream(frames)
            for name, values in http["times"].items():
                times[name] += values[warmup:]
            times["local"] += local_times[warmup:]
            difference = max([difference] + [float(np.abs(decode_image_exr(data) - image).max())
                                             for data, image in zip(http["outputs"], expected)])
    return {**http, "times": times, "difference": difference}


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

        server = None
        if args.url:
            if not args.model:
                raise SystemExit("--url needs --model: a model registered on that server")
            url, model = args.url.rstrip("/"), args.model
        else:
            env, model = register_checkpoint(work, args, checkpoint)
            server = (ProcessApi if args.server == "process" else ThreadApi)(env)
            url = server.url
        local = InProcess(checkpoint)
        try:
            http = run(url, model, frames, local, args.warmup, args.rounds, args.api_key, args.compression)
        finally:
            if server is not None:
                server.stop()

    scale = http["session"]["model"]["scale"]
    height, width = frames[0].height, frames[0].width
    difference = http["difference"]
    median = statistics.median
    times = http["times"]
    round_trip, server_ms, step_ms, local_ms = (median(times[name])
                                                for name in ("round_trip", "server", "inference", "local"))
    where = f"server {url}" if args.url else f"API in {'its own process' if args.server == 'process' else 'a thread'}"
    print(f"{label} ({model}) {width}x{height} -> {width * scale}x{height * scale}, {args.rounds} x {args.frames} "
          f"timed frames after {args.warmup}, {args.threads} torch thread(s), frame EXR "
          f"({args.compression or 'client default'}) {http['bytes_in'] / 1e6:.2f} MB in, "
          f"{http['bytes_out'] / 1e6:.2f} MB out, {where}")
    print(f"  client encode            median {median(times['encode']):8.2f} ms/frame (not in the round trip)")
    print(f"  HTTP round trip          median {round_trip:8.2f} ms/frame")
    print(f"    server (X-Server-Ms)   median {server_ms:8.2f} ms   (client + transfer: {round_trip - server_ms:.2f})")
    print(f"    step (X-Inference-Ms)  median {step_ms:8.2f} ms   (server outside the step: "
          f"{server_ms - step_ms:.2f})")
    print(f"  in-process step          median {local_ms:8.2f} ms/frame")
    print(f"  overhead ratio (round trip / in-process step) {round_trip / local_ms:.2f}x, "
          f"+{round_trip - local_ms:.2f} ms/frame")
    print(f"    (round trip / step in session {round_trip / step_ms:.2f}x: the same step, timed in the server)")
    print(f"  max |session output - in-process output| over the stream: {difference:.3g}")


if __name__ == "__main__":
    main()
