"""The measured inputs of the sizing plan (docs/operations.md, "Sizing"): what one session costs in memory, in
Redis and on the network, and one step's time on this machine's CPU.

    .venv/bin/python scripts/measure_sizing.py                      # shipped fused models + afn-m-x1, 720p and 1080p
    .venv/bin/python scripts/measure_sizing.py --size 3840x2160 --model fused-fast-x1 --steps 1

Per model and output size, through the session store itself (service.sessions.store, on the Redis of
``--redis-url`` under a key prefix of its own, removed afterwards): a session is created, ``--steps`` + 1
synthetic frames are stepped (model.io.synthetic), and its mirror is flushed. Printed and written: the history the
store holds in memory (bytes of its tensors), what one mirror write sends to Redis (the encoded history, float16 as
DENOISER_SESSION_HISTORY_PRECISION's default), how long that write takes alone, and what Redis then holds for the
session (MEMORY USAGE); the stream's bytes per frame (a frame message with the buffers the model reads, float16 and
float32, and its float16 and float32 output message: client.codec) and the POST body (an uncompressed EXR bundle,
the client's default); the median step time after the first frame. Sizes do not depend on the frames' content;
times do on the machine's load. Writes the table to ``--markdown`` (docs/results/sizing.md), the rows to ``--json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
import redis
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from client.codec import encode_bundle, encode_output  # noqa: E402
from client.rest import frame_bytes  # noqa: E402
from core.settings import Settings  # noqa: E402
from model.io.synthetic import moving_pattern_frames  # noqa: E402
from model.methods.registry import method_buffers  # noqa: E402
from service.sessions.store import SessionStore  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MODELS = ("fused-fast-x1", "fused-balanced-x1", "fused-high-x1", "fused-fast-x2", "afn-m-x1")
SIZES = ("1280x720", "1920x1080")
MB = 1e6


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", action="append", help=f"a session model (repeatable; default {', '.join(MODELS)})")
    parser.add_argument("--size", action="append", help=f"output size WxH (repeatable; default {', '.join(SIZES)})")
    parser.add_argument("--steps", type=int, default=2, help="timed frames after the first (default 2)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the session worker (default 2)")
    parser.add_argument("--redis-url", default=os.environ.get("DENOISER_REDIS_URL", "redis://127.0.0.1:6379/0"))
    parser.add_argument("--markdown", type=Path, default=REPO / "docs" / "results" / "sizing.md")
    parser.add_argument("--json", type=Path, default=REPO / "var" / "results" / "sizing.json")
    return parser.parse_args()


def tensor_bytes(value) -> int:
    """Bytes of every tensor in a (nested) state."""
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size()
    if isinstance(value, dict):
        return sum(tensor_bytes(item) for item in value.values())
    if isinstance(value, (list, tuple)):
        return sum(tensor_bytes(item) for item in value)
    if hasattr(value, "__dataclass_fields__"):
        return sum(tensor_bytes(getattr(value, name)) for name in value.__dataclass_fields__)
    return 0


def measure(model: str, size: str, args: argparse.Namespace, data_dir: Path) -> dict:
    width, height = (int(part) for part in size.split("x"))
    settings = Settings(data_dir=data_dir, redis_url=args.redis_url, session_workers=1,
                        session_threads=args.threads, session_history_precision="half")
    prefix = f"denoiser:sizing-{uuid.uuid4().hex[:8]}:"
    store = SessionStore(settings, prefix=prefix)
    client = redis.Redis.from_url(args.redis_url)
    try:
        session = store.create(model)
        scale = session.model.scale
        frames = moving_pattern_frames(args.steps + 1, (width // scale, height // scale), np.random.default_rng(0))
        results = [store.process_frame(session.id, frame) for frame in frames[:-1]]
        assert store.flush(timeout=600)
        # The last frame's mirror is held back, then written alone and timed: encoding and the Redis write.
        results.append(store.process_frame(session.id, frames[-1], start_mirror=False))
        started = time.perf_counter()
        store.start_mirror(session.id)
        assert store.flush(timeout=600), "the mirror was not written"
        mirror_ms = (time.perf_counter() - started) * 1000
        key = f"{prefix}{session.id}"
        fields = client.hgetall(key)
        mirror_bytes = sum(len(value) for name, value in fields.items() if name.startswith(b"state."))
        redis_bytes = client.memory_usage(key, samples=0)
        buffers = method_buffers(session.model.method)
        frame, output = frames[-1], results[-1].output
        if "specular_albedo" in buffers and frame.specular_albedo is None:
            # The synthetic frames have none; a renderer feeding a model that reads it sends it.
            frame = dataclasses.replace(frame, specular_albedo=frame.albedo)
        row = {
            "model": model, "output": size, "render": f"{width // scale}x{height // scale}",
            "history_memory_bytes": tensor_bytes(results[-1].session.state),
            "mirror_write_bytes": mirror_bytes, "mirror_write_ms": mirror_ms, "redis_bytes": redis_bytes,
            "frame_message_f16_bytes": len(encode_bundle(frame, dtype="float16", buffers=buffers)),
            "frame_message_f32_bytes": len(encode_bundle(frame, dtype="float32", buffers=buffers)),
            "output_message_f16_bytes": len(encode_output(output, dtype="float16", frame_index=0)),
            "output_message_f32_bytes": len(encode_output(output, dtype="float32", frame_index=0)),
            "post_exr_bytes": len(frame_bytes(frame)),
            "buffers": list(buffers),
            "step_ms": statistics.median(result.inference_ms for result in results[1:]) if args.steps else None,
            "threads": args.threads,
        }
        store.delete(session.id)
        client.delete(f"{prefix.rstrip(':')}-deleted:{session.id}")
        return row
    finally:
        store.close()


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def markdown(rows: list[dict], revision: str, load: float) -> str:
    lines = [f"Measured by `scripts/measure_sizing.py` at commit {revision}, through the session store on this "
             f"machine's CPU ({rows[0]['threads']} torch threads, shared with other work: load average {load:.1f} "
             "at the end of the run, so step and mirror times are inflated; the sizes are exact); MB = 10^6 bytes. History: the session's tensors in the API's memory; mirror: what each "
             "frame's Redis write sends (float16 history); Redis: what Redis holds for the session (MEMORY USAGE); "
             "stream in/out: one WebSocket frame message with the buffers the model reads, and its output message; "
             "POST: the frame as an uncompressed EXR bundle (the client's default); mirror ms: one mirror write alone "
             "(float16 encoding and the Redis transaction, local Redis).",
             "",
             "| model | output | render | history MB | mirror MB per frame | mirror ms | Redis MB | "
             "stream in f16 / f32 MB | stream out f16 / f32 MB | POST MB | step ms (CPU) |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        step = "-" if row["step_ms"] is None else f"{row['step_ms']:.0f}"
        lines.append(
            f"| {row['model']} | {row['output']} | {row['render']} | {row['history_memory_bytes'] / MB:.1f} | "
            f"{row['mirror_write_bytes'] / MB:.1f} | {row['mirror_write_ms']:.0f} | {row['redis_bytes'] / MB:.1f} | "
            f"{row['frame_message_f16_bytes'] / MB:.1f} / {row['frame_message_f32_bytes'] / MB:.1f} | "
            f"{row['output_message_f16_bytes'] / MB:.1f} / {row['output_message_f32_bytes'] / MB:.1f} | "
            f"{row['post_exr_bytes'] / MB:.1f} | {step} |")
    lines += ["", "Buffers each model's stream carries: " + "; ".join(
        f"{model}: {', '.join(buffers)}" for model, buffers in {r['model']: r['buffers'] for r in rows}.items()),
        "", "What these mean for a deployment (sessions per GPU, per API replica, per Redis; 1,000 sessions at "
        "1080p): [operations.md, \"Sizing\"](../operations.md#sizing)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for model in args.model or MODELS:
            for size in args.size or SIZES:
                row = measure(model, size, args, Path(work))
                rows.append(row)
                print(json.dumps({key: value for key, value in row.items() if key != "buffers"}), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(rows, indent=2))
    args.markdown.write_text(markdown(rows, commit(), os.getloadavg()[0]))
    print(f"wrote {args.markdown} and {args.json}")


if __name__ == "__main__":
    main()
