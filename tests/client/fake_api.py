"""An in-memory fake of the REST contract, served through httpx.MockTransport, for testing the client and CLI.

It speaks the contract's shapes (error shape, 201/202/204 statuses, Location headers, job records, session
frame headers and frame-index rules) without FastAPI, Redis, Celery or MLflow, so client tests do not depend on
the server's modules; a session in the denoiser layout reads frames with client.frames, so the fake runs where
torch and the model library cannot be imported (tests/client/test_torch_free.py). Jobs move along a script, one step per GET, so following them is deterministic.
"""

from __future__ import annotations

import io
import json
import re
import tarfile
import zipfile
from dataclasses import dataclass, field

import httpx
import numpy as np

from client.frames import FrameFileError, encode_image_exr, read_frame_exr
from client.rest import DenoiserClient
from core.names import JOB_KINDS


def error(status: int, code: str, message: str, details=None, headers: dict | None = None) -> httpx.Response:
    return httpx.Response(status, json={"error": {"code": code, "message": message, "details": details}},
                          headers=headers)


@dataclass
class FakeSession:
    id: str
    model: dict
    on_gap: str
    next_frame_index: int | None = None
    frames_processed: int = 0
    layout: str | dict = "denoiser"

    def record(self) -> dict:
        return {"id": self.id, "model": self.model, "created_at": "2026-01-01T00:00:00Z",
                "last_used_at": "2026-01-01T00:00:00Z", "expires_at": "2026-01-01T00:30:00Z",
                "frames_processed": self.frames_processed, "next_frame_index": self.next_frame_index,
                "on_gap": self.on_gap, "layout": self.layout}


@dataclass
class FakeApi:
    api_key: str | None = None
    datasets: dict = field(default_factory=dict)
    uploads: list = field(default_factory=list)  # (params, content-type, content-length, member names)
    jobs: dict = field(default_factory=dict)
    job_scripts: dict = field(default_factory=dict)  # job id -> list of (state, progress) still to come
    # The states and progress a new job goes through, one step per GET /jobs/{id}, ending in the last one.
    script: list = field(default_factory=lambda: [
        ("queued", {"current": 0, "total": 4, "message": "waiting for a worker", "eta_seconds": None}),
        ("running", {"current": 1, "total": 4, "message": "step 1", "eta_seconds": 3.0}),
        ("running", {"current": 1, "total": 4, "message": "step 1", "eta_seconds": 3.0}),
        ("running", {"current": 1, "total": 4, "message": "step 1", "eta_seconds": 3.0}),
        ("running", {"current": 3, "total": 4, "message": "step 3", "eta_seconds": 1.0}),
        ("succeeded", {"current": 4, "total": 4, "message": "done", "eta_seconds": 0.0}),
    ])
    final_result: dict = field(default_factory=lambda: {"psnr": 31.5})
    final_error: dict | None = None
    models: dict = field(default_factory=lambda: {
        "wskpn-xs": {"name": "wskpn-xs", "description": "small WSKPN", "latest_version": "2",
                     "aliases": {"champion": "1"},
                     "versions": [
                         {"version": "1", "run_id": "r1", "created_at": "2026-01-01T00:00:00Z",
                          "tags": {"method": "wskpn", "preset": "xs", "scale": "1"},
                          "metrics": {"validation_psnr": 30.25, "ms_per_frame": 4.5}},
                         {"version": "2", "run_id": "r2", "created_at": "2026-01-02T00:00:00Z",
                          "tags": {"method": "wskpn", "preset": "xs", "scale": "1"},
                          "metrics": {"validation_psnr": 31.0}},
                     ]},
    })
    sessions: dict = field(default_factory=dict)
    requests: list = field(default_factory=list)  # (method, path) of every request seen
    results_zip: bytes | None = None
    logs: list = field(default_factory=lambda: [f"line {i}" for i in range(10)])
    output_scale: int = 1

    def client(self, **options) -> DenoiserClient:
        options.setdefault("sleep", lambda seconds: None)
        return DenoiserClient("http://fake.test", transport=httpx.MockTransport(self.handle), **options)

    # --- dispatch ------------------------------------------------------------------------------------------

    def handle(self, request: httpx.Request) -> httpx.Response:
        request.read()  # streamed bodies (uploads) arrive as iterators
        path = request.url.path
        self.requests.append((request.method, path))
        if path == "/health":
            return httpx.Response(200, json={"status": "ok"})
        if self.api_key is not None and request.headers.get("X-API-Key") != self.api_key:
            return error(401, "unauthorized", "missing X-API-Key header: this server requires an API key")
        routes = [
            ("POST", r"/datasets", self.upload),
            ("GET", r"/datasets", lambda r: httpx.Response(200, json=list(self.datasets.values()))),
            ("GET", r"/datasets/(?P<id>[^/]+)", self.get_dataset),
            ("DELETE", r"/datasets/(?P<id>[^/]+)", self.delete_dataset),
            ("POST", r"/jobs", self.submit),
            ("GET", r"/jobs", self.list_jobs),
            ("GET", r"/jobs/(?P<id>[^/]+)", self.get_job),
            ("POST", r"/jobs/(?P<id>[^/]+)/cancel", self.cancel),
            ("GET", r"/jobs/(?P<id>[^/]+)/logs", self.job_logs),
            ("GET", r"/jobs/(?P<id>[^/]+)/results\.zip", self.results),
            ("GET", r"/models", lambda r: httpx.Response(200, json=[
                {k: v for k, v in m.items() if k != "versions"} for m in self.models.values()])),
            ("GET", r"/models/(?P<name>[^/]+)", self.get_model),
            ("PUT", r"/models/(?P<name>[^/]+)/aliases/(?P<alias>[^/]+)", self.put_alias),
            ("DELETE", r"/models/(?P<name>[^/]+)/versions/(?P<version>[^/]+)", self.delete_version),
            ("DELETE", r"/models/(?P<name>[^/]+)", self.delete_model),
            ("POST", r"/sessions", self.create_session),
            ("GET", r"/sessions/(?P<id>[^/]+)", self.get_session),
            ("DELETE", r"/sessions/(?P<id>[^/]+)", self.delete_session),
            ("POST", r"/sessions/(?P<id>[^/]+)/frames", self.frame),
        ]
        for method, pattern, handler in routes:
            match = re.fullmatch(pattern, path)
            if match and method == request.method:
                request.extensions["match"] = match.groupdict()
                return handler(request)
        return error(404, "not_found", f"no route {request.method} {path}")

    # --- datasets ------------------------------------------------------------------------------------------

    def upload(self, request: httpx.Request) -> httpx.Response:
        body = request.content
        try:
            if body[:2] == b"PK":
                members = zipfile.ZipFile(io.BytesIO(body)).namelist()
            else:
                members = tarfile.open(fileobj=io.BytesIO(body)).getnames()
        except (tarfile.TarError, zipfile.BadZipFile):
            return error(400, "invalid_archive", "the upload is not a zip, tar or tar.gz archive")
        name = request.url.params.get("name")
        self.uploads.append((dict(request.url.params), request.headers.get("content-type"),
                             request.headers.get("content-length"), members))
        if name in self.datasets:
            return error(409, "conflict", f"dataset {name!r} already exists")
        dataset_id = name or f"dataset-{len(self.datasets) + 1:04d}"
        sequences = sorted({m.split("/")[1] for m in members if m.count("/") >= 2 and m.endswith("manifest.json")})
        frames = sum(1 for m in members if m.endswith(".exr"))
        record = {"id": dataset_id, "frames": frames, "scenes": [], "sequences": [
            {"name": s, "split": request.url.params.get("split", "train"), "scene": None, "frames": 2, "width": 6,
             "height": 4, "scales": [1, 2], "buffers": ["color"], "camera_cuts": [0]} for s in sequences],
            "splits": {"train": {"sequences": len(sequences)}}}
        self.datasets[dataset_id] = record
        return httpx.Response(201, json=record, headers={"Location": f"/datasets/{dataset_id}"})

    def get_dataset(self, request):
        dataset_id = request.extensions["match"]["id"]
        if dataset_id not in self.datasets:
            return error(404, "not_found", f"dataset {dataset_id!r} does not exist")
        return httpx.Response(200, json=self.datasets[dataset_id])

    def delete_dataset(self, request):
        dataset_id = request.extensions["match"]["id"]
        if self.datasets.pop(dataset_id, None) is None:
            return error(404, "not_found", f"dataset {dataset_id!r} does not exist")
        return httpx.Response(204)

    # --- jobs ----------------------------------------------------------------------------------------------

    def submit(self, request):
        body = json.loads(request.content)
        if body.get("kind") not in JOB_KINDS:
            return error(422, "invalid_request", f"invalid request: body.kind: Input should be one of "
                                                 f"{', '.join(JOB_KINDS)}")
        dataset = (body.get("params") or {}).get("dataset")
        if dataset is not None and dataset not in self.datasets:
            return error(404, "not_found", f"dataset {dataset!r} does not exist")
        job_id = f"job-{len(self.jobs) + 1:04d}"
        device = body.get("device", "cpu")
        job = {"id": job_id, "kind": body["kind"], "state": "queued", "params": body.get("params") or {},
               "device": device, "queue": "gpu" if device == "gpu" else "cpu",
               "created_at": "2026-01-01T00:00:00Z", "started_at": None, "finished_at": None,
               "progress": {"current": 0, "total": None, "message": "queued", "eta_seconds": None},
               "mlflow_run_id": None, "mlflow_url": None, "result": None, "error": None, "attempts": 0}
        self.jobs[job_id] = job
        self.job_scripts[job_id] = list(self.script)
        return httpx.Response(202, json=job, headers={"Location": f"/jobs/{job_id}"})

    def list_jobs(self, request):
        jobs = list(self.jobs.values())
        for key in ("kind", "state"):
            if key in request.url.params:
                jobs = [job for job in jobs if job[key] == request.url.params[key]]
        return httpx.Response(200, json=jobs)

    def _job(self, request):
        return self.jobs.get(request.extensions["match"]["id"])

    def get_job(self, request):
        job = self._job(request)
        if job is None:
            return error(404, "not_found", f"job {request.extensions['match']['id']!r} does not exist")
        script = self.job_scripts.get(job["id"])
        if script and job["state"] not in ("succeeded", "failed", "cancelled"):
            state, progress = script.pop(0)
            job.update(state=state, progress=progress)
            if state == "running":
                job.update(started_at="2026-01-01T00:00:01Z", mlflow_run_id="run-1",
                           mlflow_url="http://mlflow.test/#/runs/run-1")
            if state == "succeeded":
                job.update(result=self.final_result, finished_at="2026-01-01T00:00:09Z")
            if state == "failed":
                job.update(error=self.final_error, finished_at="2026-01-01T00:00:09Z")
        return httpx.Response(200, json=job)

    def cancel(self, request):
        job = self._job(request)
        if job is None:
            return error(404, "not_found", "no such job")
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return error(409, "conflict", f"job {job['id']} already {job['state']}")
        job["state"] = "cancelled"
        return httpx.Response(202, json=job)

    def job_logs(self, request):
        lines = int(request.url.params.get("lines", 100))
        return httpx.Response(200, json={"lines": self.logs[-lines:]})

    def results(self, request):
        if self.results_zip is None:
            return error(409, "conflict", "job has no results yet")
        return httpx.Response(200, content=self.results_zip, headers={"Content-Type": "application/zip"})

    # --- models --------------------------------------------------------------------------------------------

    def get_model(self, request):
        name = request.extensions["match"]["name"]
        if name not in self.models:
            return error(404, "not_found", f"registered model {name!r} does not exist")
        return httpx.Response(200, json=self.models[name])

    def put_alias(self, request):
        name, alias = request.extensions["match"]["name"], request.extensions["match"]["alias"]
        version = json.loads(request.content).get("version")
        model = self.models.get(name)
        if model is None:
            return error(404, "not_found", f"registered model {name!r} does not exist")
        if version not in {v["version"] for v in model["versions"]}:
            return error(404, "not_found", f"model {name!r} has no version {version!r}")
        model["aliases"][alias] = version
        return httpx.Response(200, json={"name": name, "alias": alias, "version": version})

    def delete_version(self, request):
        name, version = request.extensions["match"]["name"], request.extensions["match"]["version"]
        model = self.models.get(name)
        if model is None or version not in {v["version"] for v in model["versions"]}:
            return error(404, "not_found", f"version {version} of model {name!r} does not exist")
        model["versions"] = [v for v in model["versions"] if v["version"] != version]
        return httpx.Response(204)

    def delete_model(self, request):
        name = request.extensions["match"]["name"]
        if self.models.pop(name, None) is None:
            return error(404, "not_found", f"model {name!r} does not exist")
        return httpx.Response(204)

    # --- sessions ------------------------------------------------------------------------------------------

    def create_session(self, request):
        body = json.loads(request.content)
        model = self.models.get(body["model"])
        if model is None:
            return error(404, "not_found", f"registered model {body['model']!r} does not exist")
        version = body.get("version") or (model["aliases"].get(body["alias"]) if body.get("alias") else
                                          model["latest_version"])
        if version is None:
            return error(404, "not_found", f"model {body['model']!r} has no alias {body['alias']!r}")
        session = FakeSession(f"s{len(self.sessions) + 1}", {"name": model["name"], "version": version,
                                                             "method": "wskpn", "preset": "xs",
                                                             "scale": self.output_scale, "params": 1000},
                              body.get("on_gap", "reset"), layout=body.get("layout", "denoiser"))
        self.sessions[session.id] = session
        return httpx.Response(201, json=session.record(), headers={"Location": f"/sessions/{session.id}"})

    def get_session(self, request):
        session = self.sessions.get(request.extensions["match"]["id"])
        if session is None:
            return error(404, "not_found", "session does not exist or expired")
        return httpx.Response(200, json=session.record())

    def delete_session(self, request):
        if self.sessions.pop(request.extensions["match"]["id"], None) is None:
            return error(404, "not_found", "session does not exist or expired")
        return httpx.Response(204)

    def frame(self, request):
        session = self.sessions.get(request.extensions["match"]["id"])
        if session is None:
            return error(404, "not_found", "session does not exist or expired")
        try:  # as the server reads it: in the session's layout
            if session.layout == "denoiser":
                frame = read_frame_exr(request.content)
                given, ignored = frame.frame_index is not None, []
            else:
                from model.layouts import layout_from_value, read_layout_frame_bytes

                read = read_layout_frame_bytes(request.content, layout_from_value(session.layout), "request body",
                                               mode="live")
                frame, given, ignored = read.frame, read.frame_index_given, read.ignored_channels
        except (ValueError, FrameFileError) as problem:
            return error(400, "invalid_frame", str(problem))
        color = frame.buffers["color"] if hasattr(frame, "buffers") else frame.color
        index = frame.frame_index if given else (session.next_frame_index or 0)
        if session.next_frame_index is None:
            history = "started"
        elif frame.camera_cut and index == session.next_frame_index:
            history = "reset-camera-cut"
        elif index == session.next_frame_index:
            history = "continued"
        elif index > session.next_frame_index:
            if session.on_gap == "reject":
                return error(409, "frame_gap", f"frame {index} skips frames after {session.next_frame_index - 1}")
            history = "reset-gap"
        else:
            return error(409, "frame_out_of_order", f"frame {index} comes before {session.next_frame_index}")
        session.next_frame_index = index + 1
        session.frames_processed += 1
        scale = self.output_scale
        # A recognisable "denoised" output: half the noisy color, repeated to the output resolution.
        rgb = np.repeat(np.repeat(color * 0.5, scale, axis=0), scale, axis=1)
        data = encode_image_exr(rgb)
        headers = {"Content-Type": "image/x-exr", "X-Frame-Index": str(index), "X-Inference-Ms": "1.5",
                   "X-Server-Ms": "2.25", "X-History": history}
        if ignored:
            headers["X-Ignored-Channels"] = ", ".join(ignored)
        return httpx.Response(200, content=data, headers=headers)
