"""What a session costs over the network: per-frame round trip of POST /sessions/{id}/frames and of the session's
WebSocket (GET /sessions/{id}/stream) against method.step in process.

    .venv/bin/python scripts/bench_session_overhead.py                          # jnds:xs, 128x128 -> 256x256
    .venv/bin/python scripts/bench_session_overhead.py --method munet:xs --frames 60 --threads 1
    .venv/bin/python scripts/bench_session_overhead.py --checkpoint runs/jnds-s/last.pt --data data/seq_0
    .venv/bin/python scripts/bench_session_overhead.py --checkpoint pretrained/wskpn-s-x1/model.pt \
        --size 1920x1080 --stream-dtype float16 --in-flight 1 2 --no-http --threads 1   # 1080p, frames sent ahead
    .venv/bin/python scripts/bench_session_overhead.py --url http://gpu-box:8000 --model jnds-s-x2@champion \\
        --checkpoint jnds-s.pt --api-key "$DENOISER_API_KEY"

Without ``--url`` the API is started here (its own process by default, ``--server thread`` in this one) on a
temporary data folder, and the method is registered there; with ``--url`` the model must already be registered.
Timed per frame, median over ``--frames``: the client's encode, the HTTP and WebSocket round trips, the server's
and the step's own times (from the answers), the step in process, and a bare WebSocket echo (the transport's floor);
for the WebSocket also the time from one output to the next, with ``--in-flight`` frames sent ahead.
The sides run in alternating blocks (``--rounds``), so the server's Redis write after a frame never runs beside the
in-process step. The overhead ratio is round trip / in-process step. What each timing covers, and why blocks:
docs/benchmark.md, "scripts/bench_session_overhead.py".
"""

from __future__ import annotations

import argparse
import contextlib
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

from model.training.checkpoint import load_method, save_checkpoint  # noqa: E402
from model.io.exr import decode_image_exr  # noqa: E402
from model.io.frames import FrameBundle  # noqa: E402
from model.deployment.inference_forms import load_form_table, with_inference_forms  # noqa: E402
from model.deployment.malloc import tune_for_large_frames  # noqa: E402
from model.methods.base import FrameBatch  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from client.rest import FRAME_COMPRESSIONS, DenoiserClient, frame_bytes  # noqa: E402
from client.codec import DTYPES, encode_bundle  # noqa: E402
from model.io.synthetic import moving_pattern_frames  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", default="jnds:xs", help="NAME:PRESET to build (default jnds:xs)")
    parser.add_argument("--scale", type=int, default=2, help="output / render resolution (default 2)")
    parser.add_argument("--checkpoint", type=Path, help="a model.training.checkpoint file instead of --method")
    parser.add_argument("--model", help="already registered model: NAME, NAME/VERSION or NAME@ALIAS")
    parser.add_argument("--url", help="a running API (default: start one here, see --server)")
    parser.add_argument("--server", choices=("process", "thread"), default="process",
                        help="without --url: run the API as its own uvicorn process (default) or in a thread here")
    parser.add_argument("--compression", choices=sorted(FRAME_COMPRESSIONS), default=None,
                        help="EXR compression of the frames sent (default: the client's, "
                             "client.rest.FRAME_COMPRESSION)")
    parser.add_argument("--stream-dtype", choices=sorted(DTYPES), default="float32",
                        help="dtype of the WebSocket's frames and outputs (default float32: outputs equal HTTP's)")
    parser.add_argument("--all-buffers", action="store_true",
                        help="WebSocket frames carry every buffer the frame has (default: the buffers the session's "
                             "method reads, as DenoiserClient.open_stream sends them)")
    parser.add_argument("--api-key", default=os.environ.get("DENOISER_API_KEY"), help="X-API-Key for --url")
    parser.add_argument("--redis-url", default=os.environ.get("DENOISER_REDIS_URL", "redis://127.0.0.1:6379/0"),
                        help="Redis of the in-process API (session mirror)")
    parser.add_argument("--data", type=Path, help="a sequence folder or dataset folder to take frames from")
    parser.add_argument("--size", type=render_size, default=(128, 128),
                        help="render resolution of synthetic frames: N (square) or WxH (default 128)")
    parser.add_argument("--frames", type=int, default=30, help="timed frames (default 30)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed frames first (default 5)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="alternating HTTP / in-process blocks of the whole stream (default 3)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    parser.add_argument("--in-flight", type=int, nargs="+", default=[1],
                        help="WebSocket frames sent ahead of their outputs (SessionStream.send_many; default 1: "
                             "each frame waits for the previous output, as SessionStream.send does); several "
                             "values: one WebSocket stream each, every round")
    parser.add_argument("--no-http", action="store_true", help="time the WebSocket only (large frames: half the time)")
    return parser.parse_args()


# --- frames ----------------------------------------------------------------------------------------------


def render_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    try:
        return int(width), int(height or width)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or WxH, got {text!r}") from None


def synthetic_frames(count: int, size: tuple[int, int], seed: int = 0) -> list[FrameBundle]:
    return moving_pattern_frames(count, size, np.random.default_rng(seed))


def dataset_frames(path: Path, count: int) -> list[FrameBundle]:
    """``count`` frames of the sequence at ``path`` (or a dataset's first sequence), cycled, renumbered 0..count-1."""
    from model.io.dataset import Dataset, DatasetError, Sequence

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
        from core.tracking import MLflowTracker

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
    """``uvicorn service.http.app:app`` as a child process (the deployment's program), stopped on ``stop()``."""

    def __init__(self, env: dict) -> None:
        from core.settings import get_settings

        port = free_port()
        environment = {**os.environ, **env}
        environment.pop("DENOISER_API_KEY", None)
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), environment.get("PYTHONPATH")]))
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "service.http.app:app", "--host", "127.0.0.1", "--port", str(port),
             "--log-level", "warning", "--no-access-log",
             # as `denoiser serve` does: a WebSocket message may be as large as a frame may be (1080p frames)
             "--ws-max-size", str(get_settings().max_frame_bytes)], cwd=REPO, env=environment)
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
        from core.settings import get_settings

        get_settings.cache_clear()
        from service.http.app import create_app

        port = free_port()
        self.server = uvicorn.Server(uvicorn.Config(create_app(), host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=self.server.run, daemon=True)
        thread.start()
        self.url = f"http://127.0.0.1:{port}"
        wait_until_up(self.url, thread.is_alive, "the in-process API")

    def stop(self) -> None:
        self.server.should_exit = True


# A bare ASGI app served by uvicorn like the API: it answers every WebSocket message with a message of the size its
# query string names, and does nothing else. Its round trip is what the transport alone costs on this machine.
ECHO_SERVER = """
import sys
import uvicorn

async def app(scope, receive, send):
    if scope["type"] != "websocket":
        return
    answer = bytes(int(scope["query_string"] or b"0"))
    await receive()
    await send({"type": "websocket.accept"})
    while (await receive())["type"] != "websocket.disconnect":
        await send({"type": "websocket.send", "bytes": answer})

uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), ws_max_size=int(sys.argv[2]), log_level="warning")
"""


class EchoServer:
    """ECHO_SERVER as a child process, stopped on ``stop()``."""

    def __init__(self, max_bytes: int) -> None:
        port = free_port()
        self.process = subprocess.Popen([sys.executable, "-c", ECHO_SERVER, str(port), str(max_bytes)])
        self.url = f"ws://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=1):
                return
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise SystemExit("the WebSocket echo server did not start")
            time.sleep(0.1)

    def times(self, bytes_in: int, bytes_out: int, count: int) -> list[float]:
        """Round trips (ms) of ``count`` messages of ``bytes_in`` answered with ``bytes_out``, over one connection
        opened as client.stream opens a session's (websockets' sync client, no compression)."""
        from websockets.sync.client import connect

        message, times = bytes(bytes_in), []
        with connect(f"{self.url}/?{bytes_out}", max_size=None, compression=None, ping_interval=None) as socket_:
            for _ in range(count):
                started = time.perf_counter()
                socket_.send(message)
                socket_.recv()
                times.append((time.perf_counter() - started) * 1000)
        return times

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(30)


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
    """The same method stepping through the same frames here, a new history per stream (its networks in the
    measured inference form, as the API runs them with the default DENOISER_INFERENCE_FORMS)."""

    def __init__(self, checkpoint: Path) -> None:
        self.method = with_inference_forms(load_method(checkpoint).for_inference(), load_form_table("measured"))

    def stream(self, frames: list[FrameBundle]) -> tuple[list[np.ndarray], list[float]]:
        state, outputs, times = None, [], []
        for frame in frames:
            batch = FrameBatch.from_bundles([frame], scale=None)
            with torch.inference_mode():  # as the API steps
                started = time.perf_counter()
                output, state = self.method.step(batch, state)
                times.append((time.perf_counter() - started) * 1000)
            outputs.append(output[0].permute(1, 2, 0).numpy().copy())
        return outputs, times


def timed_stream(client: DenoiserClient, model: str, frames: list[FrameBundle], encode, open_sender) -> dict:
    """Each frame encoded (``encode(frame) -> bytes``) and sent to a new session (``open_sender(session_id)``: a
    context manager giving ``send(bytes) -> (output, FrameInfo)``): outputs and per-frame times."""
    times: dict[str, list[float]] = {"encode": [], "round_trip": [], "server": [], "inference": []}
    outputs, sizes = [], []
    session = client.create_session(**session_body(model), on_gap="reject")
    try:
        with open_sender(session["id"]) as send:
            for frame in frames:
                started = time.perf_counter()
                body = encode(frame)
                times["encode"].append((time.perf_counter() - started) * 1000)
                output, info = send(body)
                outputs.append(output)
                sizes.append(len(body))
                times["round_trip"].append(info.round_trip_ms)
                times["server"].append(info.server_ms)
                times["inference"].append(info.inference_ms)
    finally:
        client.delete_session(session["id"])
    return {"session": session, "times": times, "outputs": outputs, "bytes_in": sizes[-1]}


def http_stream(client: DenoiserClient, model: str, frames: list[FrameBundle], compression: str | None) -> dict:
    """Each frame encoded as an EXR and POSTed; outputs are the answers' EXR bytes."""
    options = {} if compression is None else {"compression": compression}
    result = timed_stream(client, model, frames, lambda frame: frame_bytes(frame, **options),
                          lambda session_id: contextlib.nullcontext(
                              lambda body: client.send_frame_raw(session_id, body)))
    return {**result, "bytes_out": len(result["outputs"][-1])}


def websocket_stream(client: DenoiserClient, model: str, frames: list[FrameBundle], dtype: str,
                     all_buffers: bool = False, in_flight: int = 1) -> dict:
    """Every frame packed first (the buffers the stream sends: the session's method's unless ``all_buffers``),
    then sent over one WebSocket with ``in_flight`` frames ahead of their outputs (SessionStream.send_many);
    outputs are (H, W, 3) float32 arrays. Besides the timed_stream times, ``period``: from one output's arrival to
    the next (what a renderer streaming frames waits per frame)."""
    times: dict[str, list[float]] = {"encode": [], "round_trip": [], "server": [], "inference": [], "period": []}
    outputs, arrivals = [], []
    session = client.create_session(**session_body(model), on_gap="reject")
    try:
        with client.open_stream(session["id"], dtype=dtype, output_dtype=dtype, all_buffers=all_buffers) as stream:
            bodies = []
            for frame in frames:
                started = time.perf_counter()
                bodies.append(encode_bundle(frame, dtype=dtype, output_dtype=dtype, buffers=stream.buffers))
                times["encode"].append((time.perf_counter() - started) * 1000)
            for output, info in stream.send_many(bodies, in_flight=in_flight):
                arrivals.append(time.perf_counter())
                outputs.append(output)
                times["round_trip"].append(info.round_trip_ms)
                times["server"].append(info.server_ms)
                times["inference"].append(info.inference_ms)
    finally:
        client.delete_session(session["id"])
    # The first frame has no output before it: its period is its round trip.
    times["period"] = [times["round_trip"][0]] + [(b - a) * 1000 for a, b in zip(arrivals, arrivals[1:])]
    return {"session": session, "times": times, "outputs": outputs, "bytes_in": len(bodies[-1]),
            "bytes_out": outputs[-1].size * np.dtype(dtype).itemsize}


def run(url: str, model: str, frames: list[FrameBundle], local: InProcess, echo: EchoServer | None, warmup: int,
        rounds: int, api_key: str | None, compression: str | None, stream_dtype: str,
        all_buffers: bool = False, in_flights: tuple[int, ...] = (1,), http: bool = True) -> dict:
    """``rounds`` x (the stream over HTTP, over the WebSocket once per ``in_flights`` value, as many bare echoes of
    its messages' sizes, then in process); times of frames after ``warmup`` in each stream. The WebSocket streams
    are keyed ``websocket`` (one frame in flight) and ``websocket xN``."""
    sockets = [("websocket" if count == 1 else f"websocket x{count}", count) for count in in_flights]
    transports = (["http"] if http else []) + [key for key, _ in sockets]
    names = ("encode", "round_trip", "server", "inference", "period")
    times = {transport: {name: [] for name in names} for transport in transports}
    times["local"], times["echo"] = [], []
    difference = dict.fromkeys(transports, 0.0)
    sizes = {}
    with DenoiserClient(url, api_key=api_key, timeout=120) as client:
        for _ in range(rounds):
            results = {"http": http_stream(client, model, frames, compression)} if http else {}
            for key, count in sockets:
                results[key] = websocket_stream(client, model, frames, stream_dtype, all_buffers, count)
            streamed = results[sockets[0][0]]
            if echo is not None:
                times["echo"] += echo.times(streamed["bytes_in"], streamed["bytes_out"], len(frames))[warmup:]
            expected, local_times = local.stream(frames)
            times["local"] += local_times[warmup:]
            for transport, result in results.items():
                for name, values in result["times"].items():
                    times[transport][name] += values[warmup:]
                images = ([decode_image_exr(data) for data in result["outputs"]] if transport == "http"
                          else result["outputs"])
                difference[transport] = max([difference[transport]] + [
                    float(np.abs(image - reference).max()) for image, reference in zip(images, expected)])
                sizes[transport] = (result["bytes_in"], result["bytes_out"])
    return {"session": streamed["session"], "times": times, "difference": difference, "bytes": sizes}


def main() -> None:
    from core.settings import get_settings

    args = parse_args()
    torch.set_num_threads(args.threads)
    tune_for_large_frames()  # as the API's session threads and the CLI have it, so the in-process step is alike
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
        echo = None if args.url else EchoServer(get_settings().max_frame_bytes)  # loopback only: beside our API
        try:
            result = run(url, model, frames, local, echo, args.warmup, args.rounds, args.api_key, args.compression,
                         args.stream_dtype, args.all_buffers, tuple(args.in_flight), not args.no_http)
        finally:
            if echo is not None:
                echo.stop()
            if server is not None:
                server.stop()

    scale = result["session"]["model"]["scale"]
    height, width = frames[0].height, frames[0].width
    median = statistics.median
    times = result["times"]
    local_ms = median(times["local"])
    where = f"server {url}" if args.url else f"API in {'its own process' if args.server == 'process' else 'a thread'}"
    print(f"{label} ({model}) {width}x{height} -> {width * scale}x{height * scale}, {args.rounds} x {args.frames} "
          f"timed frames after {args.warmup}, {args.threads} torch thread(s), {where}")
    print(f"  in-process step          median {local_ms:8.2f} ms/frame")
    sent = "every buffer" if args.all_buffers else "the method's buffers"
    labels = {} if args.no_http else {"http": f"HTTP POST, frame EXR ({args.compression or 'client default'})"}
    for count in args.in_flight:
        labels["websocket" if count == 1 else f"websocket x{count}"] = (
            f"WebSocket, {args.stream_dtype} arrays, {sent}, {count} frame(s) in flight")
    for transport, label_text in labels.items():
        numbers = times[transport]
        round_trip, server_ms, step_ms = (median(numbers[name]) for name in ("round_trip", "server", "inference"))
        bytes_in, bytes_out = result["bytes"][transport]
        print(f"  {label_text}: {bytes_in / 1e6:.2f} MB in, {bytes_out / 1e6:.2f} MB out")
        print(f"    client encode          median {median(numbers['encode']):8.2f} ms/frame (not in the round trip)")
        print(f"    round trip             median {round_trip:8.2f} ms/frame   {round_trip / local_ms:.2f}x the "
              f"in-process step, +{round_trip - local_ms:.2f} ms/frame")
        print(f"    server                 median {server_ms:8.2f} ms   (client + transfer: "
              f"{round_trip - server_ms:.2f})")
        print(f"    step in the session    median {step_ms:8.2f} ms   (server outside the step: "
              f"{server_ms - step_ms:.2f}; round trip / this step {round_trip / step_ms:.2f}x)")
        if numbers.get("period"):
            period = median(numbers["period"])
            print(f"    output to output       median {period:8.2f} ms/frame   {period / local_ms:.2f}x the "
                  f"in-process step, {period / step_ms:.2f}x the session's step")
        print(f"    max |session output - in-process output| over the stream: {result['difference'][transport]:.3g}")
    if not times["echo"]:
        return
    echo_ms = median(times["echo"])
    first = "websocket" if args.in_flight[0] == 1 else f"websocket x{args.in_flight[0]}"
    rest = median(times[first]["round_trip"]) - local_ms - echo_ms
    print("  bare WebSocket echo (uvicorn, the stream's message sizes, no session)")
    print(f"    round trip             median {echo_ms:8.2f} ms/frame   the transport alone: the stream's round trip "
          f"is the in-process step + {echo_ms:.2f} + {rest:.2f} ms")


if __name__ == "__main__":
    main()
