"""Load and fault drill against an isolated stack: its own Redis, API and worker, started and stopped here.

    .venv/bin/python scripts/drill.py                      # everything (about 10 minutes on 2 busy cores)
    .venv/bin/python scripts/drill.py --sessions 8 --frames 12 --skip kills

Prints a line per case and writes every figure to WORK/results.json (summarised in docs/results/drill*.md):

- sessions: N concurrent sessions streaming frames, p50 and p95 of the client's round trip and of the server's
  time (X-Server-Ms), and whether any session's output differs from the same method stepped in process over that
  session's own frames (a crossed history would), first alone, then with a training job running on the worker;
- kills: kill -9 of the worker during a training job (the job resumes from its checkpoint on a new worker), of the
  API during streams (the sessions continue exactly from Redis), and of Redis (the queued job, the job records and
  the session mirrors are there after its restart from the append-only file);
- outage: Redis killed under a streaming session and back, the client idle, then the API killed: whether the
  session's Redis copy caught up without a request, and whether the restarted API continued or lost the history;
- bombs: decompression and archive bombs and deeply nested JSON, each with the API's answer and the API's peak
  memory (VmHWM, reset before each) against its memory before;
- decoding: frames whose decode would be large (127 unused channels at the pixel limit, an 8192x8192 reference part a
  session never reads), alone and several at once: the answers, the API's peak memory and its memory after each;
- access: the API restarted with an API key and owner tokens: docs, session lists and frames answer only to holders.

Nothing here touches the shared Redis or the default data folder: Redis runs on --redis-port with its files under
--work, which is deleted first. Thread budgets of the stack: DENOISER_SESSION_WORKERS / _THREADS and
DENOISER_JOB_THREADS from the environment (defaults here: 2 session workers of 1 thread, 1 job thread).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import threading
import time
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402
import OpenEXR  # noqa: E402
import redis  # noqa: E402
import torch  # noqa: E402

from model.training.checkpoint import load_method, save_checkpoint  # noqa: E402
from model.io.dataset import Dataset, SequenceWriter  # noqa: E402
from model.io.exr import encode_frame_exr  # noqa: E402
from model.io.frames import FrameBundle  # noqa: E402
from model.methods.base import inference_outputs  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from model.io.synthetic import moving_pattern_frames  # noqa: E402
from client.rest import DenoiserClient  # noqa: E402

MODEL = "drill-jnds-xs-x2"


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=REPO / "var" / "drill", help="deleted and recreated")
    parser.add_argument("--redis-port", type=int, default=6391)
    parser.add_argument("--api-port", type=int, default=8791)
    parser.add_argument("--sessions", type=int, default=16)
    parser.add_argument("--frames", type=int, default=24, help="frames per session")
    parser.add_argument("--size", type=int, default=32, help="render resolution of the frames (output 2x)")
    parser.add_argument("--big-size", type=int, default=256,
                        help="also stream the sessions beside one session of frames this large (0: no)")
    parser.add_argument("--skip", nargs="*", default=[], choices=["sessions", "training", "kills", "bombs",
                                                                         "decoding", "outage", "access"])
    return parser.parse_args()


# --- frames and the model ------------------------------------------------------------------------------------


def frames_of(seed: int, count: int, size: int, references: bool = False) -> list[FrameBundle]:
    """Valid frames of a moving pattern, different for every seed (so crossed histories show)."""
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0, 6, size=3)
    return moving_pattern_frames(count, size, rng, phases=phases, frequency=(0.2, 0.1), references=references)


def register_model(work: Path, tracking_uri: str) -> Path:
    from core.tracking import MLflowTracker

    torch.manual_seed(0)
    method = build_method("jnds:xs", scale=2)
    checkpoint = save_checkpoint(work / "jnds-xs.pt", method=method)
    tracker = MLflowTracker(tracking_uri, experiment="drill")
    tracker.start({"method": method.label})
    tracker.log_model(checkpoint, MODEL, {"method": method.name, "preset": method.preset, "scale": "2",
                                          "params": str(method.parameter_count())})
    tracker.finish("FINISHED")
    return checkpoint


def write_dataset(root: Path, size: int) -> Path:
    dataset = Dataset.create(root)
    for name, split, seed in (("alpha", "train", 101), ("beta", "train", 102), ("gamma", "validation", 103)):
        with SequenceWriter(root / name, name) as writer:
            for frame in frames_of(seed, 8, size, references=True):
                writer.add(frame)
        dataset.add_sequence_dir(name, split)
    return root


# --- the stack -------------------------------------------------------------------------------------------------


class Stack:
    """Redis, the API and a worker as child processes in their own process groups."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.work = args.work
        self.url = f"http://127.0.0.1:{args.api_port}"
        self.redis_url = f"redis://127.0.0.1:{args.redis_port}/0"
        self.env = {**os.environ, "PYTHONPATH": str(REPO), "DENOISER_DATA_DIR": str(self.work / "data"),
                    "DENOISER_REDIS_URL": self.redis_url, "DENOISER_WORKER_HEARTBEAT_SECONDS": "2"}
        for name, default in (("DENOISER_SESSION_WORKERS", "2"), ("DENOISER_SESSION_THREADS", "1"),
                              ("DENOISER_JOB_THREADS", "1"), ("DENOISER_MAX_SESSIONS", "64")):
            self.env.setdefault(name, default)
        self.env.pop("DENOISER_API_KEY", None)
        self.env.pop("DENOISER_TRACKING_URI", None)
        self.processes: dict[str, subprocess.Popen] = {}

    def _start(self, name: str, command: list[str]) -> None:
        log = (self.work / f"{name}.log").open("ab")
        self.processes[name] = subprocess.Popen(command, cwd=REPO, env=self.env, stdout=log, stderr=log,
                                                start_new_session=True)

    def start_redis(self) -> None:
        folder = self.work / "redis"
        folder.mkdir(parents=True, exist_ok=True)
        self._start("redis", ["redis-server", "--port", str(self.args.redis_port), "--bind", "127.0.0.1",
                              "--dir", str(folder), "--appendonly", "yes", "--appendfsync", "everysec",
                              "--save", ""])
        client = redis.Redis.from_url(self.redis_url)
        self._wait(lambda: client.ping(), "Redis")

    def start_api(self) -> None:
        self._start("api", [sys.executable, "-m", "uvicorn", "service.http.app:app", "--host", "127.0.0.1", "--port",
                            str(self.args.api_port), "--log-level", "warning", "--no-access-log"])
        self._wait(lambda: httpx.get(f"{self.url}/health", timeout=1).status_code == 200, "the API")

    def start_worker(self) -> None:
        self._start("worker", [sys.executable, "-m", "celery", "-A", "core.celery_app", "worker", "--pool=solo",
                               "--queues=cpu", "--loglevel=WARNING", "--hostname=drill@%h"])

    def kill(self, name: str) -> None:
        """kill -9, no warning: what a crash or an OOM kill does."""
        process = self.processes.pop(name)
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()

    def stop(self, name: str) -> None:
        process = self.processes.pop(name, None)
        if process is None or process.poll() is not None:
            return
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()

    def stop_all(self) -> None:
        for name in ("api", "worker", "redis"):
            self.stop(name)

    def pid(self, name: str) -> int:
        return self.processes[name].pid

    def _wait(self, check, what: str, seconds: float = 120) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                if check():
                    return
            except Exception:  # not up yet
                pass
            time.sleep(0.2)
        raise SystemExit(f"[drill] {what} did not start: see {self.work}")


def wait_for(check, what: str, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.5)
    raise SystemExit(f"[drill] timed out waiting for {what}")


# --- sessions ------------------------------------------------------------------------------------------------


def percentile(values: list[float], fraction: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(fraction * (len(ordered) - 1))))]


def stream_sessions(url: str, streams: list[list[bytes]], start: int = 0, stop: int | None = None,
                    session_ids: list[str] | None = None) -> tuple[list[str], dict[str, list], dict, dict]:
    """Stream frames start..stop of every stream through its own session, all at once (one thread each)."""
    ids = session_ids or [DenoiserClient(url).create_session(MODEL, version="1")["id"] for _ in streams]
    outputs: dict[str, list] = {session_id: [] for session_id in ids}
    round_trips: dict[str, list[float]] = {session_id: [] for session_id in ids}
    server: dict[str, list[float]] = {session_id: [] for session_id in ids}
    lock = threading.Lock()
    errors: list[str] = []

    def run(session_id: str, frames: list[bytes]) -> None:
        from model.io.exr import decode_image_exr

        with DenoiserClient(url, timeout=300) as client:
            for body in frames[start:stop]:
                try:
                    data, info = client.send_frame_raw(session_id, body)
                except Exception as error:  # reported, not hidden
                    errors.append(f"{session_id}: {error}")
                    return
                with lock:
                    round_trips[session_id].append(info.round_trip_ms)
                    server[session_id].append(info.server_ms)
                outputs[session_id].append(decode_image_exr(data))

    threads = [threading.Thread(target=run, args=(sid, frames)) for sid, frames in zip(ids, streams)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if errors:
        raise SystemExit(f"[drill] frames failed: {errors[:3]}")
    return ids, outputs, round_trips, server


def crossing(outputs: list[list[np.ndarray]], expected: list[list[np.ndarray]]) -> float:
    """The largest difference between a session's outputs and its own frames' in-process outputs."""
    return max(float(np.abs(a - b).max()) for got, want in zip(outputs, expected) for a, b in zip(got, want))


def sessions_phase(stack: Stack, args, streams, expected, label: str, results: dict, measured: int | None = None
                   ) -> None:
    """Latency over the first ``measured`` sessions (default all; the others are load, e.g. one big session)."""
    started = time.perf_counter()
    ids, outputs, per_session, per_session_server = stream_sessions(stack.url, streams)
    elapsed = time.perf_counter() - started
    worst = crossing([outputs[i] for i in ids], expected)
    round_trips = [ms for i in ids[:measured] for ms in per_session[i]]
    server = [ms for i in ids[:measured] for ms in per_session_server[i]]
    results[label] = {"sessions": len(ids), "frames": len(round_trips), "p50_ms": percentile(round_trips, 0.5),
                      "p95_ms": percentile(round_trips, 0.95), "server_p50_ms": percentile(server, 0.5),
                      "server_p95_ms": percentile(server, 0.95), "max_difference": worst,
                      "frames_per_second": len(round_trips) / elapsed}
    r = results[label]
    print(f"[drill] sessions {label}: {r['sessions']} sessions, {r['frames']} frames timed, round trip p50 "
          f"{r['p50_ms']:.1f} ms p95 {r['p95_ms']:.1f} ms (server p50 {r['server_p50_ms']:.1f} p95 "
          f"{r['server_p95_ms']:.1f}), {r['frames_per_second']:.1f} frames/s, largest difference from in-process "
          f"{worst:.2e} ({'no crossing' if worst < 1e-4 else 'MISMATCH'})", flush=True)
    for session_id in ids:
        DenoiserClient(stack.url).delete_session(session_id)


# --- training ------------------------------------------------------------------------------------------------


def start_training(client: DenoiserClient, steps: int) -> str:
    job = client.submit_job("train", {"dataset": "drill", "method": "wskpn:xs", "scale": 1, "steps": steps,
                                      "crop": 16, "batch": 2, "frames_per_sample": 2, "checkpoint_every": 10,
                                      "validate_every": 1_000_000, "warmup_steps": 0})
    return job["id"]


def job_progress(client: DenoiserClient, job_id: str) -> tuple[str, int, int]:
    job = client.get_job(job_id)
    progress = job.get("progress") or {}
    return job["state"], int(progress.get("current") or 0), int(job.get("attempts") or 0)


# --- bombs ---------------------------------------------------------------------------------------------------


def zero_exr(width: int, height: int) -> bytes:
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    stream = io.BytesIO()
    OpenEXR.File(header, {"color": np.zeros((height, width, 3), np.float32)}).write(stream)
    return stream.getvalue()


def zip_of(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return buffer.getvalue()


def zero_zip(unpacked: int) -> bytes:
    buffer = io.BytesIO()
    chunk = bytes(1024 * 1024)
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as bundle:
        with bundle.open("seq/frame_0000.exr", "w", force_zip64=True) as member:
            for _ in range(unpacked // len(chunk)):
                member.write(chunk)
    return buffer.getvalue()


def zero_tar_gz(unpacked: int) -> bytes:
    class Zeros(io.RawIOBase):
        def __init__(self, size: int) -> None:
            self.left = size

        def readable(self) -> bool:
            return True

        def readinto(self, buffer) -> int:
            count = min(len(buffer), self.left)
            buffer[:count] = bytes(count)
            self.left -= count
            return count

    out = io.BytesIO()
    with tarfile.open(fileobj=out, mode="w:gz", compresslevel=1) as bundle:
        info = tarfile.TarInfo("seq/frame_0000.exr")
        info.size = unpacked
        bundle.addfile(info, io.BufferedReader(Zeros(unpacked)))
    return out.getvalue()


def memory_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def bombs_phase(stack: Stack, results: dict) -> None:
    client = DenoiserClient(stack.url, timeout=300)
    session = client.create_session(MODEL, version="1")["id"]
    exr_2k, exr_4k = zero_exr(2048, 2048), zero_exr(4096, 4096)
    cases = [
        ("session frame, zero EXR declaring 2048x2048", "POST", f"/sessions/{session}/frames", exr_2k,
         "image/x-exr"),
        ("session frame, zero EXR declaring 4096x4096", "POST", f"/sessions/{session}/frames", exr_4k,
         "image/x-exr"),
        ("frame upload, zero EXR declaring 4096x4096", "POST", "/datasets/bombs/sequences/s/frames", exr_4k,
         "image/x-exr"),
        ("archive holding a zero EXR declaring 4096x4096", "POST", "/datasets?name=bomb1",
         zip_of({"seq/manifest.json": b"{}", "seq/frame_0000.exr": exr_4k}), "application/zip"),
        ("zip of 2 GiB of zeros", "POST", "/datasets?name=bomb2", zero_zip(2 * 1024**3), "application/zip"),
        ("tar.gz of 1 GiB of zeros", "POST", "/datasets?name=bomb3", zero_tar_gz(1024**3), "application/gzip"),
        ("archive whose manifest.json is '[' x 100000", "POST", "/datasets?name=bomb4",
         zip_of({"seq/manifest.json": b"[" * 100_000, "seq/frame_0000.exr": b"x"}), "application/zip"),
        ("JSON body '[' x 100000", "POST", "/jobs", b"[" * 100_000, "application/json"),
        ("JSON body with a 5000-digit integer", "POST", "/jobs", b'{"kind": ' + b"9" * 5000 + b"}",
         "application/json"),
    ]
    pid = stack.pid("api")
    results["bombs"] = []
    for label, method, path, body, content_type in cases:
        Path(f"/proc/{pid}/clear_refs").write_text("5")  # resets VmHWM to the current resident size
        before = memory_kb(pid, "VmRSS")
        response = httpx.request(method, stack.url + path, content=body, headers={"Content-Type": content_type},
                                 timeout=300)
        peak = memory_kb(pid, "VmHWM")
        code = response.json().get("error", {}).get("code") if response.headers.get("content-type", "").startswith(
            "application/json") else None
        row = {"bomb": label, "bytes": len(body), "status": response.status_code, "code": code,
               "rss_before_mb": before / 1024, "peak_mb": peak / 1024}
        results["bombs"].append(row)
        print(f"[drill] bomb: {label} ({len(body) / 1024:.0f} KB): {response.status_code} {code}; API memory "
              f"{row['rss_before_mb']:.0f} MB before, peak {row['peak_mb']:.0f} MB", flush=True)
    client.delete_session(session)


def decoding_phase(stack: Stack, results: dict) -> None:
    # The builders the tests use, so the drill sends the same files the tests refuse.
    from tests.builders import aov_bomb, with_reference_part

    client = DenoiserClient(stack.url, timeout=300)
    sessions = [client.create_session(MODEL, version="1")["id"] for _ in range(2)]
    bomb = aov_bomb(2048, 1024)  # 127 float channels no layout reads: about 1 MB, 1.07 GB decoded
    valid = encode_frame_exr(frames_of(7, 1, 1024)[0])
    with_x8 = with_reference_part(valid, 8)  # an 8192x8192 reference_x8 part beside a valid 1024x1024 frame

    def frame(index: int, body: bytes):
        return ("POST", f"/sessions/{sessions[index]}/frames", body)

    def upload(index: int, body: bytes):
        return ("POST", f"/datasets/decoding/sequences/s{index}/frames", body)

    cases = [
        ("session frame, 127 unused channels at 2048x1024", [frame(0, bomb)]),
        ("frame upload, 127 unused channels at 2048x1024", [upload(0, bomb)]),
        ("2 session frames at once, 127 unused channels", [frame(0, bomb), frame(1, bomb)]),
        ("2 session frames and 2 uploads at once, 127 unused channels",
         [frame(0, bomb), frame(1, bomb), upload(0, bomb), upload(1, bomb)]),
        ("session frame 1024x1024 with an 8192x8192 reference_x8 part", [frame(0, with_x8)]),
        ("session frame 1024x1024, valid", [frame(1, valid)]),
    ]
    pid = stack.pid("api")
    start = memory_kb(pid, "VmRSS")
    results["decoding"] = {"rss_start_mb": start / 1024, "cases": []}
    for label, requests in cases:
        Path(f"/proc/{pid}/clear_refs").write_text("5")  # resets VmHWM to the current resident size
        before = memory_kb(pid, "VmRSS")
        answers: list = [None] * len(requests)

        def send(index: int, method: str, path: str, body: bytes) -> None:
            response = httpx.request(method, stack.url + path, content=body, timeout=300,
                                     headers={"Content-Type": "image/x-exr"})
            code = response.json().get("error", {}).get("code") if response.status_code >= 400 else None
            answers[index] = f"{response.status_code}{' ' + code if code else ''}"

        started = time.perf_counter()
        threads = [threading.Thread(target=send, args=(index, *request)) for index, request in enumerate(requests)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        seconds = time.perf_counter() - started
        peak = memory_kb(pid, "VmHWM")
        time.sleep(1)
        after = memory_kb(pid, "VmRSS")
        row = {"case": label, "bytes": sum(len(r[2]) for r in requests), "answers": answers, "seconds": seconds,
               "rss_before_mb": before / 1024, "peak_mb": peak / 1024, "rss_after_mb": after / 1024}
        results["decoding"]["cases"].append(row)
        print(f"[drill] decoding: {label}: {', '.join(answers)} in {seconds:.2f} s; API memory {before / 1024:.0f} MB "
              f"before, peak {peak / 1024:.0f} MB, {after / 1024:.0f} MB after", flush=True)
    end = memory_kb(pid, "VmRSS")
    for session in sessions:
        client.delete_session(session)
    time.sleep(1)
    closed = memory_kb(pid, "VmRSS")
    results["decoding"].update(rss_end_mb=end / 1024, rss_after_close_mb=closed / 1024)
    print(f"[drill] decoding: API memory {start / 1024:.0f} MB at the start, {end / 1024:.0f} MB at the end, "
          f"{closed / 1024:.0f} MB once the 2 sessions are closed", flush=True)


# --- kills ---------------------------------------------------------------------------------------------------


def kill_worker_phase(stack: Stack, client: DenoiserClient, results: dict) -> None:
    job_id = start_training(client, 400)
    wait_for(lambda: job_progress(client, job_id)[1] >= 25, "training progress", 600)
    _, at_kill, _ = job_progress(client, job_id)
    stack.kill("worker")
    print(f"[drill] kill -9 worker at step {at_kill} of job {job_id}", flush=True)
    time.sleep(31)  # the lease (30 s) lapses: the next worker's start-up recovery re-sends the job
    stack.start_worker()

    def resume_lines() -> list[str]:
        return [line for line in client.job_logs(job_id, 200) if "resuming from" in line]

    wait_for(lambda: bool(resume_lines()), "the resumed attempt", 300)
    resumed = resume_lines()
    state, step, attempts = job_progress(client, job_id)
    client.cancel_job(job_id)
    results["kill_worker"] = {"step_at_kill": at_kill, "attempts": attempts, "step_after": step,
                              "resumed_line": resumed[-1] if resumed else None}
    print(f"[drill] kill -9 worker: job back on a new worker (attempt {attempts}, step {step}); "
          f"log: {resumed[-1] if resumed else 'no resume line'}", flush=True)


def kill_api_phase(stack: Stack, args, streams, expected, results: dict) -> None:
    half = args.frames // 2
    count = min(4, len(streams))
    ids, first, _, _ = stream_sessions(stack.url, streams[:count], 0, half)
    DenoiserClient(stack.url).get_session(ids[0])  # the last frames' mirrors are written before a session's next use
    time.sleep(1)
    stack.kill("api")
    stack.start_api()
    _, rest, _, _ = stream_sessions(stack.url, streams[:count], half, None, session_ids=ids)
    worst = crossing([first[i] + rest[i] for i in ids], expected[:count])
    # A history kept in Redis as float16 (the default precision) comes back rounded: outputs then differ by
    # that rounding, not by a lost or crossed history, which would differ by far more.
    precision = stack.env.get("DENOISER_SESSION_HISTORY_PRECISION", "half")
    tolerance = 1e-4 if precision == "float" else 5e-3
    verdict = ("continued exactly" if worst < 1e-4 else
               f"continued, within float16 history rounding ({precision} history)" if worst < tolerance else "MISMATCH")
    results["kill_api"] = {"sessions": count, "max_difference": worst, "history_precision": precision,
                           "verdict": verdict}
    print(f"[drill] kill -9 API after {half} frames of {count} sessions: restarted, streams continued, largest "
          f"difference from in-process {worst:.2e} ({verdict})", flush=True)
    for session_id in ids:
        DenoiserClient(stack.url).delete_session(session_id)


def kill_redis_phase(stack: Stack, client: DenoiserClient, args, streams, results: dict) -> None:
    stack.stop("worker")  # so a job stays queued
    session = client.create_session(MODEL, version="1")["id"]
    for body in streams[0][:3]:
        client.send_frame_raw(session, body)
    job_id = start_training(client, 3)
    before = redis.Redis.from_url(stack.redis_url)
    jobs_before = len(list(before.scan_iter(match="denoiser:job:*")))
    queued_before = before.llen("cpu")
    time.sleep(2)  # appendfsync everysec: what was written a second ago is on disk
    stack.kill("redis")
    stack.start_redis()
    after = redis.Redis.from_url(stack.redis_url)
    jobs_after = len(list(after.scan_iter(match="denoiser:job:*")))
    queued_after = after.llen("cpu")
    mirror = after.exists(f"denoiser:session:{session}")
    info = client.send_frame_raw(session, streams[0][3])[1]
    stack.start_worker()
    wait_for(lambda: client.get_job(job_id)["state"] in ("succeeded", "failed", "cancelled"), "the queued job", 600)
    final = client.get_job(job_id)["state"]
    results["kill_redis"] = {"job_keys_before": jobs_before, "job_keys_after": jobs_after, "queued_before":
                             queued_before, "queued_after": queued_after, "session_mirror": bool(mirror),
                             "next_frame_history": info.history, "queued_job_final_state": final}
    print(f"[drill] kill -9 Redis: job keys {jobs_before} -> {jobs_after}, queued messages {queued_before} -> "
          f"{queued_after}, session mirror {'kept' if mirror else 'LOST'} (next frame: {info.history}), the "
          f"queued job then {final}", flush=True)
    client.delete_session(session)


def redis_outage_phase(stack: Stack, client: DenoiserClient, args, streams, expected, results: dict) -> None:
    """Redis dies under a streaming session and comes back; the client pauses (no request at all) until the
    session's mirror holds every frame or 60 s pass; then the API is killed and the stream goes on."""
    from model.io.exr import decode_image_exr

    before, during = args.frames // 3, 2 * args.frames // 3
    session = client.create_session(MODEL, version="1")["id"]
    outputs, histories = [], []

    def send(frames: list[bytes]) -> None:
        for body in frames:
            data, info = client.send_frame_raw(session, body)
            outputs.append(decode_image_exr(data))
            histories.append(info.history)

    send(streams[0][:before])
    stack.kill("redis")
    send(streams[0][before:during])
    stack.start_redis()
    mirror = redis.Redis.from_url(stack.redis_url)

    def mirrored_frames() -> int | None:
        raw = mirror.hget(f"denoiser:session:{session}", "meta")
        return None if raw is None else json.loads(raw)["next_frame_index"]

    started = time.monotonic()
    while mirrored_frames() != during and time.monotonic() - started < 60:
        time.sleep(0.2)
    landed, waited = mirrored_frames(), time.monotonic() - started
    view = client.get_session(session).get("mirror")
    stack.kill("api")
    stack.start_api()
    send(streams[0][during:])
    after = histories[during]
    worst = crossing([outputs], expected[:1])
    results["redis_outage_idle"] = {
        "frames_before": before, "frames_during": during - before, "histories_during": sorted(set(
            histories[before:during])), "mirrored_next_frame_index": landed, "seconds_until_mirrored": waited,
        "mirror_view": view, "history_after_api_restart": after, "history_lost": after != "continued",
        "max_difference": worst}
    print(f"[drill] Redis down for frames {before}..{during - 1} ({sorted(set(histories[before:during]))}), back, "
          f"client idle: Redis held next_frame_index {landed} after {waited:.1f} s; kill -9 API; frame {during}: "
          f"{after} ({'history LOST' if after != 'continued' else 'history kept'}), largest difference from "
          f"in-process {worst:.2e}", flush=True)
    client.delete_session(session)


# --- access --------------------------------------------------------------------------------------------------


def access_phase(stack: Stack, body: bytes, results: dict) -> None:
    """The API restarted with an API key and owner tokens: the docs and the sessions answer only to their holders.
    The previous environment and API come back at the end, so later phases run as before."""
    import secrets

    key = secrets.token_urlsafe(32)
    saved = {name: stack.env.get(name) for name in ("DENOISER_API_KEY", "DENOISER_SESSION_OWNER_TOKENS")}
    stack.env.update(DENOISER_API_KEY=key, DENOISER_SESSION_OWNER_TOKENS="true")
    stack.kill("api")
    stack.start_api()
    statuses: list[int] = []
    failed: list[str] = []
    checks = 0
    http = httpx.Client(base_url=stack.url, timeout=300,
                        event_hooks={"response": [lambda response: statuses.append(response.status_code)]})

    def check(label: str, response: httpx.Response, wanted: tuple[int, ...]) -> httpx.Response:
        nonlocal checks
        checks += 1
        if response.status_code not in wanted:
            failed.append(f"{label}: {response.status_code}, wanted {'/'.join(map(str, wanted))}")
        return response

    keyed = {"X-API-Key": key}
    try:
        for path in ("/openapi.json", "/docs", "/redoc"):
            check(f"{path} without the key", http.get(path), (401,))
            check(f"{path} with the key", http.get(path, headers=keyed), (200,))
        check("/health without the key", http.get("/health"), (200,))
        created = [check("POST /sessions with the key", http.post("/sessions", json={"model": MODEL, "version": "1"},
                                                                  headers=keyed), (201,)).json() for _ in range(2)]
        (a, token_a), (b, token_b) = ((s.get("id"), s.get("token")) for s in created)
        if not (token_a and token_b):
            failed.append("a created session carries no owner token")
        listed = check("GET /sessions with A's token", http.get("/sessions", headers={
            **keyed, "X-Session-Token": token_a or ""}), (200,)).json()
        if [s["id"] for s in listed] != [a]:
            failed.append(f"GET /sessions with A's token listed {[s['id'] for s in listed]}, wanted only {a}")
        unlisted = check("GET /sessions without a token", http.get("/sessions", headers=keyed), (200,)).json()
        if unlisted:
            failed.append(f"GET /sessions without a token listed {len(unlisted)} sessions, wanted none")
        frame = {**keyed, "Content-Type": "image/x-exr"}
        crossed = check("a frame to B's session with A's token", http.post(
            f"/sessions/{b}/frames", content=body, headers={**frame, "X-Session-Token": token_a or ""}), (403, 404))
        check("a frame to B's session with B's token", http.post(
            f"/sessions/{b}/frames", content=body, headers={**frame, "X-Session-Token": token_b or ""}), (200,))
        for session, token in ((a, token_a), (b, token_b)):
            check("DELETE a session with its token", http.delete(
                f"/sessions/{session}", headers={**keyed, "X-Session-Token": token or ""}), (200, 204))
    finally:
        http.close()
        for name, value in saved.items():
            if value is None:
                stack.env.pop(name, None)
            else:
                stack.env[name] = value
        stack.kill("api")
        stack.start_api()
    restored = httpx.get(f"{stack.url}/openapi.json", timeout=60)  # the API without a key again, for later phases
    statuses.append(restored.status_code)
    check("/openapi.json without a key after the restore", restored, (200,))
    errors = sum(status >= 500 for status in statuses)
    code = crossed.json().get("error", {}).get("code") if crossed.status_code >= 400 else None
    results["access"] = {"tried": len(statuses), "checks": checks, "5xx": errors, "failed": failed,
                         "crossed_frame": f"{crossed.status_code} {code}"}
    print(f"[drill] access (API key, owner tokens): docs without and with the key, /health without it, GET /sessions "
          f"with A's token and with none, B's frame with A's token ({crossed.status_code} {code}), the API restored: "
          f"{len(statuses)} requests, {errors} 5xx, {checks - len(failed)} of {checks} checks passed"
          f"{'' if not failed else '; FAILED: ' + '; '.join(failed)}", flush=True)


# --- main ----------------------------------------------------------------------------------------------------


def main() -> None:
    args = parse_args()
    torch.set_num_threads(1)  # the in-process references, as the API's session workers run them
    shutil.rmtree(args.work, ignore_errors=True)
    (args.work / "data" / "mlflow").mkdir(parents=True)
    stack = Stack(args)
    results: dict = {"settings": {k: stack.env[k] for k in ("DENOISER_SESSION_WORKERS", "DENOISER_SESSION_THREADS",
                                                            "DENOISER_JOB_THREADS")},
                     "cpu_count": os.cpu_count(), "load_average_at_start": os.getloadavg()}
    print(f"[drill] {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}; {results['settings']}",
          flush=True)
    checkpoint = register_model(args.work, f"sqlite:///{args.work / 'data' / 'mlflow' / 'mlflow.db'}")
    streams_frames = [frames_of(seed, args.frames, args.size) for seed in range(args.sessions)]
    streams = [[encode_frame_exr(frame) for frame in frames] for frames in streams_frames]
    expected = [inference_outputs(load_method(checkpoint), frames) for frames in streams_frames]
    try:
        stack.start_redis()
        stack.start_api()
        stack.start_worker()
        client = DenoiserClient(stack.url, timeout=300)
        client.upload_dataset(write_dataset(args.work / "dataset", 16), name="drill")
        if "sessions" not in args.skip:
            sessions_phase(stack, args, streams, expected, "alone", results)
            if args.big_size:
                big = frames_of(999, args.frames, args.big_size)
                sessions_phase(stack, args, streams[:-1] + [[encode_frame_exr(f) for f in big]],
                               expected[:-1] + [inference_outputs(load_method(checkpoint), big)],
                               f"alone, {len(streams) - 1} timed beside one at {args.big_size}x{args.big_size}",
                               results, measured=len(streams) - 1)
        if "training" not in args.skip:
            job_id = start_training(client, 1_000_000)
            wait_for(lambda: job_progress(client, job_id)[1] >= 3, "the training job to run", 600)
            ready = httpx.get(f"{stack.url}/ready", timeout=10)
            results["ready_while_training"] = {"status": ready.status_code, **ready.json()}
            print(f"[drill] /ready while the only worker trains: {ready.status_code}, "
                  f"{ready.json()['workers_detail']}", flush=True)
            if "sessions" not in args.skip:
                sessions_phase(stack, args, streams, expected, "with training", results)
            client.cancel_job(job_id)
            wait_for(lambda: client.get_job(job_id)["state"] == "cancelled", "the cancel", 120)
        if "bombs" not in args.skip:
            bombs_phase(stack, results)
        if "decoding" not in args.skip:
            decoding_phase(stack, results)
        if "kills" not in args.skip:
            kill_worker_phase(stack, client, results)
            kill_api_phase(stack, args, streams, expected, results)
            kill_redis_phase(stack, DenoiserClient(stack.url, timeout=300), args, streams, results)
        if "outage" not in args.skip:
            redis_outage_phase(stack, DenoiserClient(stack.url, timeout=300), args, streams, expected, results)
        if "access" not in args.skip:
            access_phase(stack, streams[0][0], results)
    finally:
        stack.stop_all()
    results["load_average_at_end"] = os.getloadavg()
    (args.work / "results.json").write_text(json.dumps(results, indent=2, default=str))
    print(f"[drill] done; results in {args.work / 'results.json'}", flush=True)


if __name__ == "__main__":
    main()
