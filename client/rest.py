"""A Python client of the denoiser REST API (httpx): datasets, jobs, models, sessions.

    from client.rest import DenoiserClient

    with DenoiserClient("http://127.0.0.1:8000", api_key="...") as client:
        dataset = client.upload_dataset("data/demo")                    # a folder is tarred on the fly
        job = client.submit_job("train", {"dataset": dataset.id, "method": "wskpn:xs", "steps": 200})
        job = client.wait_job(job.id, on_progress=lambda j: print(j.progress.current))
        session = client.create_session("wskpn-xs", alias="champion")
        summary = client.stream_sequence(session.id, "data/demo/glass_s2", "out/glass_s2")
        image, info = client.send_arrays(session.id, color=..., albedo=..., normal=..., depth=..., motion=...)

Answers are typed (client.answers: Session, Job, Dataset, Model, ...) and still read as dicts. Frames are read and
written with client.frames (NumPy, OpenEXR), never torch or the model library. Every non-2xx answer raises ``ApiClientError(status, code, message, details)`` built from the server's error
shape ``{"error": {"code", "message", "details"}}``; a server that cannot be reached at all raises
``ServerUnreachable`` naming the URL. The client holds no state besides its connection pool, so one instance can
be shared by threads (httpx.Client is thread-safe).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import statistics
import tarfile
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import httpx

from client.answers import Dataset, FrameResult, Job, Model, ModelVersion, Session
from core.names import FINISHED_STATES

if TYPE_CHECKING:  # numpy and OpenEXR load only when frames are sent
    import numpy as np

    from client.frames import Frame
    from client.stream import SessionStream

DEFAULT_URL = "http://127.0.0.1:8000"
API_KEY_HEADER = "X-API-Key"
SESSION_TOKEN_HEADER = "X-Session-Token"  # owner tokens of sessions (service.http.routes.sessions)
EXR_MEDIA_TYPE = "image/x-exr"
MANIFEST = "manifest.json"
STREAM_TRANSPORTS = ("http", "websocket")  # how stream_sequence sends frames
# Lossless OpenEXR compressions a frame can be sent with (the server reads any of them). Uncompressed by default:
# ZIP saves a third to two thirds of a noisy frame's bytes (more on smooth buffers) but makes writing and reading a
# frame several times slower, which pays only on a link slower than about 1 Gbit/s.
FRAME_COMPRESSIONS = ("none", "rle", "zips", "zip", "piz")
FRAME_COMPRESSION = "none"
# Archive suffix -> Content-Type. The server sniffs magic bytes anyway; the header is a courtesy.
ARCHIVE_TYPES = {".zip": "application/zip", ".tar": "application/x-tar", ".tgz": "application/gzip",
                 ".tar.gz": "application/gzip", ".gz": "application/gzip"}


class ApiClientError(Exception):
    """The server answered with a non-2xx status; carries its error shape."""

    def __init__(self, status: int, code: str, message: str, details: Any = None) -> None:
        super().__init__(status, code, message, details)
        self.status = status
        self.code = code
        self.message = message
        self.details = details

    def __str__(self) -> str:
        return f"{self.status} {self.code}: {self.message}"

    @property
    def is_client_error(self) -> bool:
        """A 4xx: the request was wrong (bad input, unknown id, conflict), not the server."""
        return 400 <= self.status < 500


class ServerUnreachable(ConnectionError):
    """No HTTP answer at all: connection refused, DNS failure, timeout. The message names the URL."""

    def __init__(self, url: str, reason: str) -> None:
        super().__init__(f"cannot reach the denoiser service at {url}: {reason}")
        self.url = url
        self.reason = reason


@dataclass(frozen=True)
class FrameInfo:
    """What the server said about one denoised frame (its X-* headers) plus the client's round-trip time."""

    frame_index: int | None
    inference_ms: float | None  # method.step on the server
    server_ms: float | None  # the whole request on the server
    history: str | None  # continued | started | reset-gap | reset-camera-cut
    round_trip_ms: float  # request sent to response read, as the client saw it
    sanitized_pixels: int | None  # input pixels the server repaired (NaN / Inf / out of range)
    headers: httpx.Headers = field(repr=False, compare=False)

    @classmethod
    def from_response(cls, response: httpx.Response, round_trip_ms: float) -> FrameInfo:
        headers = response.headers
        return cls(frame_index=_optional(int, headers.get("X-Frame-Index")),
                   inference_ms=_optional(float, headers.get("X-Inference-Ms")),
                   server_ms=_optional(float, headers.get("X-Server-Ms")),
                   history=headers.get("X-History"), round_trip_ms=round_trip_ms,
                   sanitized_pixels=_optional(int, headers.get("X-Sanitized-Pixels")), headers=headers)


@dataclass
class StreamSummary:
    """The result of ``stream_sequence``: one FrameInfo per frame, the files written, and medians. ``ignored``: the
    files of the folder that are not frames (a renderer's own manifest.json, previews), which were not sent."""

    session_id: str
    out_dir: Path
    frames: list[FrameInfo]
    files: list[Path]
    wall_seconds: float
    ignored: list[str] = field(default_factory=list)
    pngs: list[Path] = field(default_factory=list)

    def median(self, attribute: str) -> float | None:
        values = [getattr(frame, attribute) for frame in self.frames if getattr(frame, attribute) is not None]
        return statistics.median(values) if values else None

    def as_dict(self) -> dict:
        histories: dict[str, int] = {}
        for frame in self.frames:
            histories[frame.history or "unknown"] = histories.get(frame.history or "unknown", 0) + 1
        return {"session": self.session_id, "frames": len(self.frames), "out_dir": str(self.out_dir),
                "wall_seconds": round(self.wall_seconds, 3),
                "frames_per_second": round(len(self.frames) / self.wall_seconds, 3) if self.wall_seconds else None,
                "median_inference_ms": self.median("inference_ms"), "median_server_ms": self.median("server_ms"),
                "median_round_trip_ms": self.median("round_trip_ms"), "history": histories,
                **({"ignored": self.ignored} if self.ignored else {}), **({"pngs": len(self.pngs)} if self.pngs else {})}


def _optional(kind: type, text: str | None):
    if text is None:
        return None
    try:
        return kind(text)
    except ValueError:
        return None


class DenoiserClient:
    """Synchronous client of one denoiser service.

    ``transport`` replaces the network (tests pass an ``httpx.MockTransport``); ``sleep`` and ``clock`` are what
    ``wait_job`` waits and measures with, replaceable for the same reason.
    """

    def __init__(self, url: str | None = None, api_key: str | None = None, timeout: float = 60.0, *,
                 transport: httpx.BaseTransport | None = None, sleep: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.url = (url or DEFAULT_URL).rstrip("/")
        headers = {API_KEY_HEADER: api_key} if api_key else {}
        # One timeout per network operation (connect, each read, each write), not for the whole request, so an
        # upload of several GB or a slow download still finishes while a dead server is noticed.
        self._http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout, transport=transport,
                                  follow_redirects=True)
        self._sleep = sleep
        self._clock = clock
        self._session_tokens: dict[str, str] = {}  # session id -> owner token, for the sessions it created

    # --- plumbing ------------------------------------------------------------------------------------------

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> DenoiserClient:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def request(self, method: str, path: str, **kwargs) -> httpx.Response:
        """Send one request; raise ApiClientError for a non-2xx answer, ServerUnreachable for no answer."""
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TransportError as error:
            raise ServerUnreachable(self.url, _transport_reason(error)) from error
        _raise_for_status(response)
        return response

    def _json(self, method: str, path: str, **kwargs) -> Any:
        return _decoded(self.request(method, path, **kwargs), method, path)

    def _download(self, path: str, destination: Path, params: dict | None = None) -> Path:
        """Stream a response body to ``destination`` (written under a temporary name, then renamed)."""
        destination.parent.mkdir(parents=True, exist_ok=True)
        temporary = destination.with_name(f".{destination.name}.{os.getpid()}.part")
        try:
            with self._http.stream("GET", path, params=params) as response:
                if response.is_error:
                    response.read()
                    _raise_for_status(response)
                with temporary.open("wb") as file:
                    for chunk in response.iter_bytes():
                        file.write(chunk)
            os.replace(temporary, destination)
        except httpx.TransportError as error:
            raise ServerUnreachable(self.url, _transport_reason(error)) from error
        finally:
            temporary.unlink(missing_ok=True)
        return destination

    # --- health --------------------------------------------------------------------------------------------

    def health(self) -> dict:
        return self._json("GET", "/health")

    def ready(self) -> dict:
        """GET /ready; a 503 (something down) is returned as its body rather than raised."""
        try:
            return self._json("GET", "/ready")
        except ApiClientError as error:
            if error.status == 503 and isinstance(error.details, dict):
                return error.details
            raise

    # --- datasets ------------------------------------------------------------------------------------------

    def upload_dataset(self, source: str | os.PathLike, name: str | None = None, split: str = "train",
                       skipped: list[str] | None = None, layout: str | None = None) -> Dataset:
        """Upload a dataset folder, a sequence folder, a folder of sequence folders, or a zip / tar(.gz).

        A folder is packed into a temporary uncompressed tar (frames are ZIP-compressed EXRs already) holding
        only what the manifests list, so stray files (previews, reports, half-written ``.partial`` folders)
        do not make the server refuse the upload; their paths are appended to ``skipped`` when given, as are the
        files the server left out of a renderer's folders (X-Ignored-Files). A manifest.json is read as this
        project's only when its ``format`` is (denoiser-sequence/1 or denoiser-dataset/1); a renderer's own is one
        more file left out. The archive is streamed from disk, never held in memory. Returns the new dataset.

        ``layout``: a built-in layout other than ``denoiser`` sends a renderer's sequence folder (frame EXRs and
        ``references/``), or a folder of them, for the server to convert (``?layout=``).
        """
        source = Path(source)
        params = {"split": split}
        if name is not None:
            params["name"] = name
        if layout is not None:
            params["layout"] = layout
        if source.is_dir():
            with tempfile.TemporaryDirectory(prefix="denoiser-upload-") as work:
                archive = Path(work) / f"{source.resolve().name or 'dataset'}.tar"
                renderer_frames = layout not in (None, "denoiser")
                left_out = pack_renderer_folder(source, archive) if renderer_frames else pack_folder(source, archive)
                if skipped is not None:
                    skipped.extend(left_out)
                return self._upload_archive(archive, "application/x-tar", params, skipped)
        if not source.is_file():
            raise FileNotFoundError(f"{source}: no such file or folder to upload")
        return self._upload_archive(source, archive_media_type(source), params, skipped)

    def _upload_archive(self, archive: Path, media_type: str, params: dict, skipped: list[str] | None) -> Dataset:
        with archive.open("rb") as file:
            # A file object is sent in chunks with a Content-Length taken from the file's size.
            response = self.request("POST", "/datasets", params=params, content=file,
                                    headers={"Content-Type": media_type})
        ignored = response.headers.get("X-Ignored-Files")
        if ignored and skipped is not None:
            skipped.extend(name.strip() for name in ignored.split(", ") if name.strip())
        return Dataset.from_dict(_decoded(response, "POST", "/datasets"))

    def list_datasets(self) -> list[Dataset]:
        return [Dataset.from_dict(item) for item in _items(self._json("GET", "/datasets"))]

    def get_dataset(self, dataset_id: str) -> Dataset:
        return Dataset.from_dict(self._json("GET", f"/datasets/{_segment(dataset_id)}"))

    def delete_dataset(self, dataset_id: str) -> None:
        self.request("DELETE", f"/datasets/{_segment(dataset_id)}")

    # --- jobs ----------------------------------------------------------------------------------------------

    def submit_job(self, kind: str, params: dict | None = None, device: str = "cpu") -> Job:
        """POST /jobs; returns the queued Job (its ``id`` is what the other job calls take)."""
        return Job.from_dict(self._json("POST", "/jobs", json={"kind": kind, "params": params or {}, "device": device}))

    def list_jobs(self, kind: str | None = None, state: str | None = None, limit: int | None = None,
                  offset: int | None = None) -> list[Job]:
        params = {key: value for key, value in
                  {"kind": kind, "state": state, "limit": limit, "offset": offset}.items() if value is not None}
        return [Job.from_dict(item) for item in _items(self._json("GET", "/jobs", params=params))]

    def get_job(self, job_id: str) -> Job:
        return Job.from_dict(self._json("GET", f"/jobs/{_segment(job_id)}"))

    def cancel_job(self, job_id: str) -> Job | None:
        """Ask for cooperative cancellation (202); the job reaches ``cancelled`` when its worker notices."""
        body = self._json("POST", f"/jobs/{_segment(job_id)}/cancel")
        return Job.from_dict(body) if isinstance(body, dict) else body

    def job_logs(self, job_id: str, lines: int | None = None) -> list[str]:
        params = {"lines": lines} if lines is not None else None
        body = self._json("GET", f"/jobs/{_segment(job_id)}/logs", params=params)
        return list(body.get("lines", [])) if isinstance(body, dict) else list(body or [])

    def wait_job(self, job_id: str, on_progress: Callable[[Job], None] | None = None, *,
                 timeout: float | None = None, interval: float = 0.5, max_interval: float = 5.0,
                 backoff: float = 1.5, unreachable_retries: int = 5) -> Job:
        """Poll the job until it is succeeded, failed or cancelled; return its final record.

        The wait between polls grows by ``backoff`` from ``interval`` up to ``max_interval`` while nothing
        changes and drops back to ``interval`` whenever the state or progress moves, so a busy job is shown
        promptly and an idle queue costs few requests. ``on_progress(job)`` is called with the first record and
        after every change. Past ``timeout`` seconds a TimeoutError names the job's last state; the job itself
        keeps running. A server that stops answering (an API restart) is polled on at the longest interval, and
        ServerUnreachable is raised only after ``unreachable_retries`` failed polls in a row.
        """
        started = self._clock()
        delay = interval
        seen = None
        failures = 0
        job = Job.from_dict({"state": "unknown"})
        while True:
            try:
                job = self.get_job(job_id)
                failures = 0
            except ServerUnreachable:
                failures += 1
                if failures > unreachable_retries:
                    raise
                self._check_deadline(job_id, job, started, max_interval, timeout)
                self._sleep(max_interval)
                continue
            snapshot = (job.get("state"), json.dumps(job.get("progress"), sort_keys=True, default=str))
            if snapshot != seen:
                seen = snapshot
                delay = interval
                if on_progress is not None:
                    on_progress(job)
            else:
                delay = min(delay * backoff, max_interval)
            if job.get("state") in FINISHED_STATES:
                return job
            self._check_deadline(job_id, job, started, delay, timeout)
            self._sleep(delay)

    def _check_deadline(self, job_id: str, job: Job, started: float, delay: float, timeout: float | None) -> None:
        if timeout is not None and self._clock() - started + delay > timeout:
            raise TimeoutError(f"job {job_id} is still {job.get('state')} after {timeout:g} s")

    def follow_job(self, job_id: str, on_progress: Callable[[Job], None], **options) -> Job:
        """``wait_job`` with a progress callback (the CLI's --follow)."""
        return self.wait_job(job_id, on_progress, **options)

    def job_results(self, job_id: str) -> dict:
        """GET /jobs/{id}/results: an infer job's sequences and frame files."""
        return self._json("GET", f"/jobs/{_segment(job_id)}/results")

    def download_results(self, job_id: str, out_dir: str | os.PathLike, *, extract: bool = True) -> list[Path]:
        """Download an infer job's results.zip into ``out_dir``; extracted (default) or kept as the zip.

        Returns the files written. Extraction refuses members that would land outside ``out_dir``.
        """
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        archive = out_dir / f"{job_id}-results.zip"
        self._download(f"/jobs/{_segment(job_id)}/results.zip", archive)
        if not extract:
            return [archive]
        try:
            return safe_extract_zip(archive, out_dir)
        finally:
            archive.unlink(missing_ok=True)

    # --- models --------------------------------------------------------------------------------------------

    def list_models(self) -> list[Model]:
        return [Model.from_dict(item) for item in _items(self._json("GET", "/models"))]

    def get_model(self, name: str) -> Model:
        return Model.from_dict(self._json("GET", f"/models/{_segment(name)}"))

    def get_model_version(self, name: str, version: str | int) -> ModelVersion:
        return ModelVersion.from_dict(self._json("GET", f"/models/{_segment(name)}/versions/{_segment(str(version))}"))

    def set_alias(self, name: str, alias: str, version: str | int) -> dict | None:
        return self._json("PUT", f"/models/{_segment(name)}/aliases/{_segment(alias)}",
                          json={"version": str(version)})

    def get_alias(self, name: str, alias: str) -> dict:
        return self._json("GET", f"/models/{_segment(name)}/aliases/{_segment(alias)}")

    def delete_alias(self, name: str, alias: str) -> None:
        self.request("DELETE", f"/models/{_segment(name)}/aliases/{_segment(alias)}")

    def delete_model_version(self, name: str, version: str | int) -> None:
        self.request("DELETE", f"/models/{_segment(name)}/versions/{_segment(str(version))}")

    def delete_model(self, name: str) -> None:
        self.request("DELETE", f"/models/{_segment(name)}")

    # --- sessions ------------------------------------------------------------------------------------------

    def create_session(self, model: str, version: str | int | None = None, alias: str | None = None,
                       on_gap: str = "reset", layout: str | dict | None = None, scale: int | None = None) -> Session:
        """``model``: a registered model, a pretrained model or a method without weights (``oidn:high``);
        ``layout``: a built-in layout's name or a layout mapping (the keys of a layout file); default denoiser;
        ``scale``: a method's output scale (default 1)."""
        if version is not None and alias is not None:
            raise ValueError("give a model version or an alias, not both")
        body = {"model": model, "version": None if version is None else str(version), "alias": alias,
                "on_gap": on_gap}
        if layout is not None:
            body["layout"] = layout
        if scale is not None:
            body["scale"] = scale
        session = Session.from_dict(self._json("POST", "/sessions", json=body))
        if session.get("token"):  # the server has owner tokens on: every later request on it sends this one
            self._session_tokens[session["id"]] = session["token"]
        return session

    def _owner(self, session_id: str) -> dict[str, str]:
        token = self._session_tokens.get(session_id)
        return {SESSION_TOKEN_HEADER: token} if token else {}

    def list_sessions(self) -> list[Session]:
        """The live sessions; where the server has owner tokens on, those this client created (it sends their
        tokens)."""
        tokens = ",".join(self._session_tokens.values())
        headers = {SESSION_TOKEN_HEADER: tokens} if tokens else {}
        return [Session.from_dict(item) for item in _items(self._json("GET", "/sessions", headers=headers))]

    def get_session(self, session_id: str) -> Session:
        return Session.from_dict(self._json("GET", f"/sessions/{_segment(session_id)}", headers=self._owner(session_id)))

    def reset_session(self, session_id: str) -> Session | None:
        body = self._json("POST", f"/sessions/{_segment(session_id)}/reset", headers=self._owner(session_id))
        return Session.from_dict(body) if isinstance(body, dict) else body

    def delete_session(self, session_id: str) -> None:
        self.request("DELETE", f"/sessions/{_segment(session_id)}", headers=self._owner(session_id))

    def send_frame_raw(self, session_id: str, frame: bytes | Frame | str | os.PathLike) -> tuple[bytes, FrameInfo]:
        """POST one frame bundle; return the output EXR's bytes as received and the frame's FrameInfo."""
        body = frame if isinstance(frame, (bytes, bytearray, memoryview)) else frame_bytes(frame)
        started = time.perf_counter()
        response = self.request("POST", f"/sessions/{_segment(session_id)}/frames", content=bytes(body),
                                headers={"Content-Type": EXR_MEDIA_TYPE, "Accept": EXR_MEDIA_TYPE,
                                         **self._owner(session_id)})
        round_trip_ms = (time.perf_counter() - started) * 1000.0
        return response.content, FrameInfo.from_response(response, round_trip_ms)

    def send_frame(self, session_id: str, frame: bytes | Frame | str | os.PathLike) -> FrameResult:
        """Denoise one frame in the session: ``frame`` is EXR bytes, a client.frames.Frame (or a model FrameBundle),
        or a frame file path.

        Returns a FrameResult: ``image``, the output as a float32 (H, W, 3) RGB array (scale x render resolution),
        and ``info``, its FrameInfo (X-Frame-Index, X-Inference-Ms, X-Server-Ms, X-History, round-trip time;
        ``.headers`` has them all).
        """
        data, info = self.send_frame_raw(session_id, frame)
        return FrameResult(decode_rgb_exr(data), info)

    def send_arrays(self, session_id: str, *, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray,
                    depth: np.ndarray, motion: np.ndarray, jitter: tuple[float, float] = (0.0, 0.0),
                    frame_index: int | None = None, camera_cut: bool = False, compression: str = FRAME_COMPRESSION,
                    **optional: np.ndarray) -> FrameResult:
        """Denoise a frame a renderer holds in memory, no file written: (H, W, 3) color, albedo, normal, (H, W)
        depth, (H, W, 2) motion in the frame bundle's conventions (docs/frame-format.md), and optionally
        specular_albedo, diffuse, specular, roughness. Sent as an in-memory EXR; ``frame_index`` None lets the
        session number it. ``open_stream(...).send_arrays`` sends the same over the WebSocket."""
        from client.frames import make_frame

        frame = make_frame(color=color, albedo=albedo, normal=normal, depth=depth, motion=motion, jitter=jitter,
                           frame_index=frame_index, camera_cut=camera_cut, **optional)
        return self.send_frame(session_id, frame_bytes(frame, compression=compression))

    def open_stream(self, session_id: str, *, dtype: str = "float32", output_dtype: str = "float32",
                    all_buffers: bool = False) -> SessionStream:
        """A WebSocket to the session (GET /sessions/{id}/stream): ``send(frame)`` gives what ``send_frame`` gives,
        without the per-frame request and EXR files (client.stream). Use it as a context manager. Frames carry only
        the buffers the session's method reads (asked once, GET /sessions/{id}), unless ``all_buffers``."""
        from client.stream import SessionStream

        buffers = None
        if not all_buffers:
            try:
                buffers = self.get_session(session_id)["model"].get("buffers")  # an older server names none
            except (ApiClientError, ServerUnreachable):  # the WebSocket gives that error (no such session, ...)
                pass
        key = self._http.headers.get(API_KEY_HEADER)
        headers = {**({API_KEY_HEADER: key} if key else {}), **self._owner(session_id)}
        return SessionStream(self.url, session_id, headers, dtype=dtype, output_dtype=output_dtype,
                             timeout=self._http.timeout.read or 60.0, buffers=buffers)

    def stream_sequence(self, session_id: str, sequence_dir: str | os.PathLike, out_dir: str | os.PathLike, *,
                        strip_references: bool = True,
                        on_frame: Callable[[FrameInfo, Path], None] | None = None, transport: str = "http",
                        layout: str | dict | None = None, png: bool = False) -> StreamSummary:
        """Send every frame of a sequence folder in order; write each output to ``out_dir/frame_%04d.exr``.

        ``transport="http"``: each frame is POSTed; the outputs are the server's EXRs byte for byte (written under
        a temporary name, then renamed). The server ignores references, so with ``strip_references`` (default)
        frames that carry them are re-encoded without them first: a scale-2 reference alone is 4x the size of the
        noisy color. A folder without this project's manifest.json (one whose ``format`` is denoiser-sequence/1) is a
        renderer's plain folder of EXRs: its .exr files are sent as they are, in name order, for the session to read
        in its layout; its other files (a renderer's own manifest.json, previews) are named in ``ignored``.

        ``transport="websocket"``: the frames are read here (a plain folder's in ``layout``, the session's, default
        denoiser) and sent over one WebSocket as float32 arrays (``open_stream``), the next frame read and sent while
        the one before steps (``SessionStream.send_many``); each output is written as a float32 RGB EXR with the same
        pixels as the server's (references are never sent). A refused frame stops the stream after the frames before
        it were written (the one sent after it is stepped, not written).

        ``png``: each output is also written as ``frame_%04d.png``, display-encoded (clip(x, 0, 1) ** (1/2.2), 8 bit).
        """
        if transport not in STREAM_TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(STREAM_TRANSPORTS)}, got {transport!r}")
        from client.frames import (encode_png, frame_file_name, is_sequence_folder, renderer_frame_files,
                                   sequence_frame_files)

        out_dir = Path(out_dir)
        bundles = is_sequence_folder(sequence_dir)
        ignored: list[str] = []
        if bundles:
            paths, has_references = sequence_frame_files(sequence_dir)
            reencode = strip_references and has_references
        else:
            (paths, ignored), reencode = renderer_frame_files(sequence_dir), False
        out_dir.mkdir(parents=True, exist_ok=True)
        infos: list[FrameInfo] = []
        files: list[Path] = []
        pngs: list[Path] = []
        with contextlib.ExitStack() as stack:
            if transport == "websocket":
                from client.stream import file_sender

                send_all = file_sender(stack.enter_context(self.open_stream(session_id)), bundles, layout)
            else:
                def send_all(frame_paths: list[Path]) -> Iterator[tuple[bytes, FrameInfo]]:
                    for frame_path in frame_paths:
                        # Read leniently when re-encoded: the session repairs NaN / Inf.
                        body = frame_bytes(frame_path) if reencode else frame_path.read_bytes()
                        yield self.send_frame_raw(session_id, body)
            started = time.perf_counter()
            for index, (data, info) in enumerate(send_all(paths)):
                path = _write_atomically(out_dir / frame_file_name(index), data)
                if png:
                    pngs.append(_write_atomically(path.with_suffix(".png"), encode_png(decode_rgb_exr(data))))
                infos.append(info)
                files.append(path)
                if on_frame is not None:
                    on_frame(info, path)
        return StreamSummary(session_id, out_dir, infos, files, time.perf_counter() - started, ignored, pngs)


# --- errors --------------------------------------------------------------------------------------------------


def _raise_for_status(response: httpx.Response) -> None:
    if response.is_success:
        return
    status = response.status_code
    code, message, details = f"http_{status}", response.reason_phrase or f"HTTP {status}", None
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and isinstance(body.get("error"), dict):
        error = body["error"]
        code = str(error.get("code") or code)
        message = str(error.get("message") or message)
        details = error.get("details")
    elif isinstance(body, dict) and "detail" in body:  # a bare FastAPI / Starlette error, e.g. from a proxy
        message = body["detail"] if isinstance(body["detail"], str) else json.dumps(body["detail"])
        details = body["detail"]
    elif response.text.strip():
        message = f"{message}: {response.text.strip()[:300]}"
    # /ready answers 503 with its whole report: keep it as the details when there is no error shape.
    if details is None and isinstance(body, dict) and "error" not in body:
        details = body
    raise ApiClientError(status, code, message, details)


def _decoded(response: httpx.Response, method: str, path: str) -> Any:
    """A 2xx answer's JSON body (None for an empty one); ApiClientError when it is not JSON."""
    if response.status_code == 204 or not response.content:
        return None
    try:
        return response.json()
    except ValueError:
        raise ApiClientError(response.status_code, "invalid_response",
                             f"{method} {path}: expected JSON, got {response.headers.get('content-type')!r}: "
                             f"{response.text[:200]!r}") from None


def _transport_reason(error: httpx.TransportError) -> str:
    if isinstance(error, httpx.ConnectError):
        text = str(error) or "connection failed"
        return "connection refused (is the server running?)" if "refused" in text.lower() else text
    if isinstance(error, httpx.TimeoutException):
        return f"timed out ({type(error).__name__})"
    return f"{type(error).__name__}: {error}"


def _items(body: Any) -> list:
    """List endpoints answer a JSON array; an envelope ({"items": [...]} or {"jobs": [...]}) is unwrapped."""
    if isinstance(body, list):
        return body
    if isinstance(body, dict):
        for key in ("items", "jobs", "datasets", "models", "sessions"):
            if isinstance(body.get(key), list):
                return body[key]
    raise ApiClientError(200, "invalid_response", f"expected a list, got {type(body).__name__}")


def _segment(value: str) -> str:
    """One path segment: ids and names must not smuggle in '/' or '..' (they would address another route)."""
    text = str(value)
    if not text or "/" in text or text in {".", ".."}:
        raise ValueError(f"{text!r} is not a valid identifier")
    return quote(text, safe="-_.~:@")


# --- archives ------------------------------------------------------------------------------------------------


def archive_media_type(path: Path) -> str:
    name = path.name.lower()
    for suffix in sorted(ARCHIVE_TYPES, key=len, reverse=True):
        if name.endswith(suffix):
            return ARCHIVE_TYPES[suffix]
    return "application/octet-stream"


def _sequence_files(folder: Path) -> list[Path]:
    """The manifest and the frame files a sequence folder's manifest lists (reads the manifest only)."""
    from client.frames import sequence_frame_files

    return [folder / MANIFEST] + sequence_frame_files(folder)[0]


def _dataset_names(manifest: Path) -> list[str]:
    from client.frames import FrameFileError

    try:
        sequences = json.loads(manifest.read_text()).get("sequences")
    except (OSError, ValueError, AttributeError):
        sequences = None
    if not isinstance(sequences, dict):
        raise FrameFileError(f"{manifest}: not a readable dataset manifest (no 'sequences' object)")
    return sorted(sequences)


def folder_members(folder: str | os.PathLike) -> tuple[list[Path], list[str]]:
    """The files of a dataset / sequence / folder of sequences that belong in an upload, and those left out.

    - a dataset folder (manifest.json, format denoiser-dataset/1): its manifest and the sequences it lists;
    - a sequence folder (format denoiser-sequence/1): its manifest and listed frames;
    - any other folder: every sub-folder holding a sequence manifest.
    Everything else (hidden files, pictures, reports, unlisted frames, a manifest.json of another format, such as a
    renderer's own) is left out and named in the second list.
    """
    from client.frames import DATASET_FORMAT, SEQUENCE_FORMAT, manifest_format

    root = Path(folder)
    manifest = root / MANIFEST
    kind = manifest_format(manifest) if manifest.is_file() else None
    if kind == DATASET_FORMAT:
        members = [manifest]
        for name in _dataset_names(manifest):
            members += _sequence_files(root / name)
    elif kind == SEQUENCE_FORMAT:
        members = _sequence_files(root)
    else:
        members = []
        for entry in sorted(root.iterdir()):
            if entry.is_dir() and not entry.name.startswith(".") and \
                    manifest_format(entry / MANIFEST) == SEQUENCE_FORMAT:
                members += _sequence_files(entry)
        if not members:
            foreign = f" ({MANIFEST} there is not this project's: its format is {kind!r})" if manifest.is_file() else ""
            raise FileNotFoundError(f"{root}: no {SEQUENCE_FORMAT} or {DATASET_FORMAT} manifest and no sequence "
                                    f"folders (each with one) inside{foreign}; nothing to upload (a renderer's "
                                    f"frames: give their layout)")
    kept = set(members)
    left_out = sorted(str(path.relative_to(root)) for path in root.rglob("*") if path.is_file() and path not in kept)
    return members, left_out


def pack_folder(folder: str | os.PathLike, archive: str | os.PathLike) -> list[str]:
    """Write the folder's upload members into an uncompressed tar under one top folder named like it.

    Returns the paths left out (relative to ``folder``). The server steps into a single wrapping folder, so a
    dataset, a sequence and a folder of sequences all arrive in the layout it expects.
    """
    root = Path(folder)
    members, left_out = folder_members(root)
    top = root.resolve().name or "upload"
    with tarfile.open(archive, "w", format=tarfile.PAX_FORMAT) as tar:
        for path in members:
            tar.add(path, arcname=str(PurePosixPath(top, *path.relative_to(root).parts)), recursive=False)
    return left_out


def pack_renderer_folder(folder: str | os.PathLike, archive: str | os.PathLike) -> list[str]:
    """``pack_folder`` for a renderer's frames (an upload with a layout): the folder is one sequence (its *.exr and
    references/*.exr) or holds one per sub-folder. Returns the files left out (anything else)."""
    root = Path(folder)

    def exrs(path: Path) -> list[Path]:
        return sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() == ".exr") if path.is_dir() else []

    sequences = [root] if exrs(root) else [entry for entry in sorted(root.iterdir()) if exrs(entry)]
    if not sequences:
        raise FileNotFoundError(f"{root}: no frame EXRs, neither in the folder nor in its sub-folders")
    members = [path for sequence in sequences for path in exrs(sequence) + exrs(sequence / "references")]
    chosen = set(members)
    left_out = sorted(str(path.relative_to(root)) for path in root.rglob("*") if path.is_file() and path not in chosen)
    top = root.resolve().name or "upload"
    with tarfile.open(archive, "w", format=tarfile.PAX_FORMAT) as tar:
        for path in members:
            tar.add(path, arcname=str(PurePosixPath(top, *path.relative_to(root).parts)), recursive=False)
    return left_out


def safe_extract_zip(archive: Path, out_dir: Path) -> list[Path]:
    """Extract every member under ``out_dir``; a member naming an absolute path or '..' is refused."""
    out_dir = out_dir.resolve()
    written = []
    with zipfile.ZipFile(archive) as zipped:
        for member in zipped.infolist():
            target = (out_dir / member.filename).resolve()
            if member.filename.startswith(("/", "\\")) or not target.is_relative_to(out_dir):
                raise ValueError(f"{archive.name}: member {member.filename!r} would be written outside {out_dir}")
            if member.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with zipped.open(member) as source, target.open("wb") as destination:
                shutil.copyfileobj(source, destination)
            written.append(target)
    return written


def _write_atomically(path: Path, data: bytes) -> Path:
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_bytes(data)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


# --- EXR -----------------------------------------------------------------------------------------------------



def frame_bytes(frame: Frame | str | os.PathLike, *, strip_references: bool = True,
                compression: str = FRAME_COMPRESSION) -> bytes:
    """A frame bundle EXR as bytes (what POST /sessions/{id}/frames takes) of a client.frames.Frame, any object
    with the buffers as attributes (a model FrameBundle), or a frame file. Shapes are checked here; values are the
    server's to check: a session repairs NaN, Inf and out-of-range values and says so (X-Sanitized-Pixels).

    A path is read as a frame first; its references are dropped (the server ignores them), so a file is sent as it
    is only with ``strip_references=False``. ``compression`` is one of FRAME_COMPRESSIONS.
    """
    from client.frames import encode_frame_exr, read_frame_exr

    if compression not in FRAME_COMPRESSIONS:
        raise ValueError(f"compression must be one of {', '.join(FRAME_COMPRESSIONS)}, got {compression!r}")
    if isinstance(frame, (str, os.PathLike)):
        if not strip_references:
            return Path(frame).read_bytes()
        frame = read_frame_exr(frame)
    return encode_frame_exr(frame, compression=compression)


def decode_rgb_exr(data: bytes) -> np.ndarray:
    """The (H, W, 3) float32 RGB of the server's output EXR; a ValueError (FrameFileError) if it is not one."""
    from client.frames import decode_image_exr

    return decode_image_exr(data, source="the server's output")
