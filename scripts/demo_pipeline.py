"""The main job's work, done through the running service exactly as a user would (REST, via the client):
render a small dataset, train a small model, register it with the alias `champion`, evaluate it next to the
pretrained fused model (registered by scripts/setup.sh with the alias `pretrained`), SVGF and OIDN on a held-out
scene, and stream the held-out sequence through inference sessions on both models.

    .venv/bin/python scripts/demo_pipeline.py [--url http://127.0.0.1:8000] [--out var/demo-output]

scripts/setup.sh starts the services and then runs this. Every step prints progress lines.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from client.rest import ApiClientError, DenoiserClient  # noqa: E402

DATASET = "demo"
MODEL = "demo-wskpn-xs"
# Shipped in pretrained/ and registered by scripts/setup.sh (denoiser pretrained --register): usable at once.
PRETRAINED = "fused-balanced-x1"
RENDERS = [  # (split, scenes, frames, seed): two training scenes, one validation sequence, one held-out scene
    ("train", ["diffuse_room", "moving_light"], 8, 1),
    ("validation", ["diffuse_room"], 4, 5),
    ("test", ["glass"], 8, 2),
]


def follow(client: DenoiserClient, job: dict, what: str) -> dict:
    print(f"[demo] {what}: job {job['id']} ({job['kind']}) queued", flush=True)
    last = {"state": None, "time": 0.0}

    def show(record: dict) -> None:
        # A line on every state change, and at most one every 3 s while the job runs.
        progress = record.get("progress") or {}
        now = time.monotonic()
        if record["state"] == last["state"] and now - last["time"] < 3:
            return
        eta = progress.get("eta_seconds")
        print(f"[demo]   {record['state']} {progress.get('current', 0)}/{progress.get('total', 0)} "
              f"{progress.get('message', '')}" + (f" (about {eta:.0f} s left)" if eta else ""), flush=True)
        last.update(state=record["state"], time=now)

    record = client.wait_job(job["id"], show)
    if record["state"] != "succeeded":
        error = record.get("error") or {}
        raise SystemExit(f"[demo] {what} {record['state']}: {error.get('message', '')}\n"
                         + "\n".join(client.job_logs(job["id"], 20)))
    return record


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", default=os.environ.get("DENOISER_URL", "http://127.0.0.1:8000"))
    parser.add_argument("--api-key", default=os.environ.get("DENOISER_API_KEY"))
    parser.add_argument("--out", type=Path, default=Path("var/demo-output"), help="where streamed frames go")
    args = parser.parse_args()
    client = DenoiserClient(args.url, api_key=args.api_key)

    for _ in range(60):  # the worker may still be starting
        try:
            if client.ready().get("status") == "ready":
                break
        except ApiClientError:
            pass
        time.sleep(1)
    else:
        raise SystemExit(f"[demo] the service at {args.url} is not ready: {client.ready()}")

    for split, scenes, frames, seed in RENDERS:
        job = client.submit_job("generate", {"dataset": DATASET, "scenes": scenes, "frames": frames, "size": 64,
                                             "ref_spp": 256, "scales": [1, 2], "seed": seed, "split": split,
                                             "overwrite": True})
        follow(client, job, f"rendering {split} sequences {', '.join(scenes)}")
    dataset = client.get_dataset(DATASET)
    print(f"[demo] dataset {DATASET}: {len(dataset['sequences'])} sequences", flush=True)

    job = client.submit_job("train", {"dataset": DATASET, "method": "wskpn:xs", "steps": 150, "crop": 32,
                                      "batch": 4, "register_as": MODEL, "validate_every": 75,
                                      "checkpoint_every": 75})
    trained = follow(client, job, "training wskpn:xs")
    version = str(trained["result"]["registered_model"]["version"])
    client.set_alias(MODEL, "champion", version)
    print(f"[demo] registered {MODEL} version {version}, alias champion; MLflow run {trained.get('mlflow_run_id')}",
          flush=True)

    job = client.submit_job("evaluate", {"dataset": DATASET, "split": "test", "vdp": False,
                                         "methods": [f"models:/{MODEL}@champion", f"models:/{PRETRAINED}@pretrained",
                                                     "svgf", "oidn:high"]})
    evaluated = follow(client, job, "evaluating on the held-out scene: the demo model, the pretrained model, SVGF, "
                                    "OIDN")
    for row in evaluated["result"]["methods"]:
        print(f"[demo]   {row['source']} ({row['label']}): PSNR {row['metrics']['psnr']:.2f} dB, "
              f"{row['ms_per_frame']:.1f} ms/frame", flush=True)

    held_out = Path(os.environ.get("DENOISER_DATA_DIR", "var")) / "datasets" / DATASET / "glass_s2"
    for name, alias, out in ((MODEL, "champion", args.out), (PRETRAINED, "pretrained", args.out / PRETRAINED)):
        session = client.create_session(name, alias=alias)
        summary = client.stream_sequence(session["id"], held_out, out)
        client.delete_session(session["id"])
        numbers = summary.as_dict()
        print(f"[demo] streamed glass_s2 ({numbers['frames']} frames) through a session on {name}@{alias} into "
              f"{out}: median {numbers['median_round_trip_ms']:.1f} ms per frame over HTTP, "
              f"{numbers['median_inference_ms']:.1f} ms of it in the model", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
