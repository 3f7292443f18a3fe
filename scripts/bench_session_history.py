"""What a session's history costs in Redis, and what storing it in float16 changes in the output.

    .venv/bin/python scripts/bench_session_history.py                                  # shipped models, 128x128
    .venv/bin/python scripts/bench_session_history.py --size 1920x1080 --model fused-balanced-x1 --model oidn-taa

Per model (a pretrained name, or a registry method such as ``oidn-taa:balanced``) and render size: two frames are
stepped, the state after them is encoded as a session mirrors it (``service.sessions.state_codec``, float32 and float16),
written to Redis the way the session store writes it (``service.sessions.store.state_fields``: one transaction, chunked
fields) and read back whole, and the third frame is stepped both from the original state and from the restored
float16 one. Printed: the state's size in memory, stored float32 and float16; encode, Redis write and read, decode
(ms); the step (ms); and how far the output continued from the float16 history is from the uninterrupted one (max
absolute difference in linear radiance, and the PSNR between the two display-encoded outputs: higher is closer). Frames are synthetic
(``model.io.synthetic``); the differences do not depend on their content much, the sizes not at all.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import redis
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.sessions.store import state_fields, state_from_fields  # noqa: E402
from model.deployment.inference_forms import load_form_table, with_inference_forms  # noqa: E402
from model.deployment.malloc import tune_for_large_frames  # noqa: E402
from model.methods.base import FrameBatch, Method  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from model.ops.tonemap import display_encode  # noqa: E402
from model.deployment.pretrained import is_pretrained, load_pretrained, pretrained_names  # noqa: E402
from service.sessions.state_codec import decode_state, encode_state  # noqa: E402
from model.io.synthetic import moving_pattern_frames  # noqa: E402


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", default=[],
                        help="pretrained name or METHOD[:PRESET] (repeat; default: every shipped model + oidn-taa)")
    parser.add_argument("--size", action="append", default=[], help="render size WxH or N (repeat; default 128)")
    parser.add_argument("--scale", type=int, default=1, help="scale of registry methods (default 1)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    parser.add_argument("--redis-url", default=os.environ.get("DENOISER_REDIS_URL", "redis://127.0.0.1:6379/0"))
    return parser.parse_args()


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height or width)


def load(name: str, scale: int) -> Method:
    method = load_pretrained(name) if is_pretrained(name) else build_method(name, scale).eval()
    return with_inference_forms(method.for_inference(), load_form_table("measured"))


def timed(function, *args):
    start = time.perf_counter()
    value = function(*args)
    return value, (time.perf_counter() - start) * 1000


def measure(method: Method, size: tuple[int, int], client: redis.Redis | None) -> dict:
    frames = [FrameBatch.from_bundles([bundle], scale=None)
              for bundle in moving_pattern_frames(3, size, np.random.default_rng(0))]
    with torch.no_grad():
        state = None
        for frame in frames[:2]:
            _, state = method.step(frame, state)
        in_memory = sum(t.numel() * t.element_size() for t in state.values())
        exact = encode_state(state, "float")
        half, encode_ms = timed(encode_state, state, "half")
        row = {"memory": in_memory, "float32": len(exact), "float16": len(half), "encode_ms": encode_ms}
        if client is not None:
            key = f"denoiser:bench-history:{uuid.uuid4().hex}"
            mapping = {"meta": "{}", **state_fields(half)}

            def write() -> None:
                pipeline = client.pipeline(transaction=True)
                pipeline.delete(key)
                pipeline.hset(key, mapping=mapping)
                pipeline.expire(key, 60)
                pipeline.execute()

            _, row["write_ms"] = timed(write)
            fields, row["read_ms"] = timed(client.hgetall, key)
            client.delete(key)
            restored, row["decode_ms"] = timed(state_from_fields, fields)
        else:
            restored, row["decode_ms"] = timed(decode_state, half)
        method.step(frames[2], state)  # the same step once untimed: its first run allocates what later ones reuse
        (reference, _), row["step_ms"] = timed(method.step, frames[2], state)
        continued, _ = method.step(frames[2], restored)
    row["max_diff"] = float((continued - reference).abs().max())
    # As the metrics compare images: display-encoded, peak 1.
    mse = float(((display_encode(continued) - display_encode(reference)) ** 2).mean())
    row["psnr"] = math.inf if mse == 0 else 10 * math.log10(1 / mse)
    return row


def megabytes(count: int) -> str:
    return f"{count / 2 ** 20:.2f}"


def main() -> None:
    args = parse_args()
    tune_for_large_frames()  # as sessions run: without it a 1080p step faults its tensors in every time
    torch.set_num_threads(args.threads)
    models = args.model or [*pretrained_names(), "oidn-taa:balanced"]
    sizes = [parse_size(text) for text in args.size] or [(128, 128)]
    client = redis.Redis.from_url(args.redis_url, socket_connect_timeout=1)
    try:
        client.ping()
    except redis.RedisError as error:
        print(f"(Redis at {args.redis_url} unreachable, write/read not timed: {error})")
        client = None
    print(f"{args.threads} torch threads; MB = 2^20 bytes; psnr: float16-restored output against the "
          "uninterrupted one, display-encoded\n")
    print("| model | render size | state in memory MB | stored float32 MB | stored float16 MB | encode ms | "
          "Redis write ms | Redis read ms | decode ms | step ms | max diff | psnr dB |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in models:
        method = load(name, args.scale)
        for size in sizes:
            row = measure(method, size, client)
            write = f"{row['write_ms']:.1f}" if "write_ms" in row else "-"
            read = f"{row['read_ms']:.1f}" if "read_ms" in row else "-"
            print(f"| {name} | {size[0]}x{size[1]} | {megabytes(row['memory'])} | {megabytes(row['float32'])} | "
                  f"{megabytes(row['float16'])} | {row['encode_ms']:.1f} | {write} | {read} | "
                  f"{row['decode_ms']:.1f} | {row['step_ms']:.1f} | {row['max_diff']:.2e} | {row['psnr']:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
