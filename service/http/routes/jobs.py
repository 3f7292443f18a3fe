"""/jobs: submit a job of any kind (``core.jobs.kinds``); follow, cancel, read logs, artifacts and results.

A submission is checked completely before anything is queued (the kind's ``check`` in ``core.jobs``: the
dataset, methods, presets, model references, sizes), stored as a job record in Redis (``core.job_store``)
and sent by task name to the Celery queue of its device under the job's id (``service.http.dispatch``). Everything after
that is the worker's; the record is what GET shows.
"""

from __future__ import annotations

import io
import logging
import re
import zipfile
from collections.abc import Iterator
from pathlib import Path as FilePath
from typing import Annotated, Any, Literal

import redis
from fastapi import APIRouter, Body, Depends, Path, Query, Response
from fastapi.responses import FileResponse, StreamingResponse

from model.io.dataset import frame_file_name
from model.fit.report import LADDER_JSON, LADDER_MARKDOWN
from service.http.dispatch import get_dispatcher
from service.http.errors import ApiError, documented_error, domain_errors
from service.http.identifiers import JobId, SequenceName
from service.http.schemas.jobs import Job, JobCreate, JobLogs, JobResults
from core.job_store import JobStore, store_for
from core.jobs.checks import invalid
from core.jobs.dispatch import CeleryDispatcher
from core.jobs.files import CHART as QUALITY_SPEED_CHART
from core.jobs.files import (BENCHMARK_FILES, CHECKPOINT_FOLDER, COMPARISON, DDP_LOG_FILE, LOG_FILE, STABILITY_FILES,
                             tail_lines)
from core.jobs.kinds import KINDS, check
from core.jobs.specs import JobKind, JobState
from core.settings import Settings, get_settings
from core.storage import Storage, checked_id, get_storage

log = logging.getLogger("denoiser.api")



def _redis_errors() -> Iterator[None]:
    """Redis (job records, broker) unreachable: 503 naming it, not a 500."""
    try:
        yield
    except redis.RedisError as error:
        raise ApiError(503, "redis_unavailable", f"job store unavailable: {type(error).__name__}: {error}") from None


router = APIRouter(prefix="/jobs", tags=["jobs"], dependencies=[Depends(_redis_errors)])


def job_store_dependency(settings: Annotated[Settings, Depends(get_settings)]) -> JobStore:
    return store_for(settings.redis_url)


StoreDep = Annotated[JobStore, Depends(job_store_dependency)]
StorageDep = Annotated[Storage, Depends(get_storage)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
DispatcherDep = Annotated[CeleryDispatcher, Depends(get_dispatcher)]

_TYPES = {".json": "application/json", ".md": "text/markdown; charset=utf-8", ".png": "image/png"}
ARTIFACT_TYPES = {name: _TYPES[FilePath(name).suffix] for name in
                  ("report.json", "report.md", QUALITY_SPEED_CHART, *BENCHMARK_FILES, *STABILITY_FILES, LADDER_JSON,
                   LADDER_MARKDOWN)}
EXR_TYPE = "image/x-exr"
_FRAME = re.compile(r"^(?:frame_)?([0-9]{1,9})(?:\.exr)?$")  # [0-9]: \d also takes non-ASCII digits


_NOT_FOUND = documented_error("no such job", "not_found", "job '5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e' does not exist")


def _job(record: dict[str, Any]) -> Job:
    return Job.model_validate(record)


def _require(store: JobStore, job_id: str) -> dict[str, Any]:
    record = store.get(job_id)
    if record is None:
        raise ApiError(404, "not_found", f"job {job_id!r} does not exist")
    return record


# ------------------------------------------------------------------------------------------ submit

@router.post(
    "", status_code=202, response_model=Job, summary="Submit a job",
    responses={400: documented_error("the body is not JSON", "invalid_json",
                                     "the body is not valid JSON at character 10"),
               404: documented_error("a dataset, sequence, model or checkpoint named in the parameters does not exist",
                                     "dataset_not_found", "dataset 'rooms' does not exist"),
               409: documented_error("the job would overwrite something", "sequence_exists",
                                     "dataset 'rooms' already has sequence(s) metals_s0; use another seed or set "
                                     "overwrite"),
               422: documented_error("invalid parameters (the message names the field or the problem)",
                                     "unknown_preset", "method 'wskpn' has no preset 'xxl'; presets: xs, s, m, l"),
               415: documented_error("the body was not sent as application/json", "unsupported_media_type",
                                     "Content-Type text/plain is not accepted here; send the body as JSON with "
                                     "Content-Type application/json"),
               503: documented_error("the queue (Redis) or the model registry is unreachable", "queue_unavailable",
                                     "could not queue the job: Error 111 connecting to 127.0.0.1:6379")},
)
def submit_job(body: Annotated[JobCreate, Body()], response: Response, store: StoreDep, storage: StorageDep,
               settings: SettingsDep, dispatcher: DispatcherDep) -> Job:
    """The parameters are checked against the stored datasets, the method registry and the model registry
    before anything is queued; the job then goes to queue `gpu` (device gpu) or `cpu`. Answers 202 with the job
    and `Location: /jobs/{id}`."""
    try:
        params = check(body.kind, body.params, storage, settings)
    except (ValueError, KeyError) as error:  # a library's refusal of the input (e.g. a damaged dataset manifest)
        raise invalid(error) from None
    queue = KINDS[body.kind].queue(body.device)
    record = store.create(body.kind, params, body.device, queue)
    try:
        dispatcher.send(record["id"], queue)
    except Exception as error:  # the broker is down: the job must not look queued forever
        log.exception("could not queue job %s", record["id"])
        message = f"could not queue the job: {type(error).__name__}: {error}"
        store.finish(record["id"], "failed", error={"code": "queue_unavailable", "message": message})
        raise ApiError(503, "queue_unavailable", message, {"job_id": record["id"]}) from None
    response.headers["Location"] = f"/jobs/{record['id']}"
    return _job(record)


# -------------------------------------------------------------------------------------------- read

@router.get("", response_model=list[Job], summary="List jobs, newest first",
            responses={200: {"headers": {"X-Total-Count": {"description": "jobs matching the filters",
                                                           "schema": {"type": "integer"}}}}})
def list_jobs(store: StoreDep, response: Response,
              kind: Annotated[JobKind | None, Query(description="only jobs of this kind")] = None,
              state: Annotated[JobState | None, Query(description="only jobs in this state")] = None,
              limit: Annotated[int, Query(ge=1, le=1000, description="page size")] = 50,
              offset: Annotated[int, Query(ge=0, description="jobs to skip")] = 0) -> list[Job]:
    records, total = store.list(kind=kind, state=state, limit=limit, offset=offset)
    response.headers["X-Total-Count"] = str(total)
    return [_job(r) for r in records]


@router.get("/{job_id}", response_model=Job, summary="A job: state, progress, MLflow run, result or error",
            responses={404: _NOT_FOUND})
def get_job(job_id: JobId, store: StoreDep) -> Job:
    return _job(_require(store, job_id))


@router.post("/{job_id}/cancel", status_code=202, response_model=Job, summary="Cancel a job",
             responses={404: _NOT_FOUND, 409: documented_error("the job has already finished", "job_finished",
                                                               "job '5f0c3a9e...' has already finished (succeeded)")})
def cancel_job(job_id: JobId, store: StoreDep, dispatcher: DispatcherDep) -> Job:
    """A queued job is cancelled at once (and its message revoked); a running one is flagged and stops at its
    next progress point (DDP ranks are stopped as a whole): its state turns `cancelled` shortly after."""
    with domain_errors():
        record = store.request_cancel(job_id)
    if record["state"] == "cancelled":
        try:
            dispatcher.revoke(job_id)
        except Exception:  # the record already says cancelled, which the worker honours anyway
            log.warning("could not revoke the task of job %s", job_id, exc_info=True)
    return _job(record)


@router.get("/{job_id}/logs", response_model=JobLogs, summary="The end of a job's log",
            responses={404: _NOT_FOUND})
def job_logs(job_id: JobId, store: StoreDep, storage: StorageDep,
             lines: Annotated[int, Query(ge=1, le=10_000, description="how many lines from the end")] = 200,
             source: Annotated[Literal["job", "ranks"], Query(
                 description="job: the job's log; ranks: what the DDP ranks of a train job print")] = "job",
             ) -> JobLogs:
    """The job log has the execution's own lines (start, progress every few seconds, errors with their traceback,
    and the end of the ranks' log when a DDP training ends); `source=ranks` follows the ranks while they run."""
    _require(store, job_id)
    folder = storage.job(job_id)
    path = folder / LOG_FILE if source == "job" else folder / CHECKPOINT_FOLDER / DDP_LOG_FILE
    return JobLogs(lines=tail_lines(path, lines))


@router.get("/{job_id}/artifacts/{name}", summary="A file an evaluate, benchmark, fit or stability job wrote",
            response_class=FileResponse,
            responses={200: {"content": {kind: {} for kind in ARTIFACT_TYPES.values()}}, 404: _NOT_FOUND})
def job_artifact(job_id: JobId, store: StoreDep, storage: StorageDep,
                 name: Annotated[str, Path(description="report.json, report.md (evaluate, benchmark at one "
                                                       "scale); comparison_<sequence>.png (evaluate: the last "
                                                       "frame side by side); quality_speed.png, benchmark.json, "
                                                       "benchmark.md, "
                                                       "quality_cost.png (benchmark); ladder.json, ladder.md (fit); "
                                                       "stability.json, stability.md, psnr_curves.png, "
                                                       "psnr_drop.png, ghost_curves.png (stability)")]
                 ) -> FileResponse:
    _require(store, job_id)
    path = storage.job(job_id) / name
    media_type = "image/png" if COMPARISON.match(name) else ARTIFACT_TYPES.get(name)
    if media_type is None or not path.is_file():
        raise ApiError(404, "not_found", f"job {job_id!r} has no artifact {name!r} (artifacts: "
                       f"report.json and report.md written by evaluate and benchmark jobs when they succeed, "
                       f"comparison_<sequence>.png by evaluate jobs, "
                       f"{QUALITY_SPEED_CHART} and {', '.join(BENCHMARK_FILES)} by benchmark jobs, {LADDER_JSON} "
                       f"and {LADDER_MARKDOWN} by fit jobs, {', '.join(STABILITY_FILES)} by stability jobs)")
    return FileResponse(path, media_type=media_type, filename=name)


@router.get("/{job_id}/chart.png", summary="The quality-vs-speed chart of a benchmark job (PNG)",
            response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: documented_error(
                "no such job, or the job has no chart (yet)", "no_chart",
                "job '5f0c3a9e...' has no quality-vs-speed chart: benchmark jobs draw one when they succeed")})
def job_chart(job_id: JobId, store: StoreDep, storage: StorageDep) -> FileResponse:
    """PSNR and FLIP against ms per frame (log scale), the Pareto front drawn and every method labelled: the
    chart `denoiser benchmark` draws (`model/evaluation/benchmark.py`), for the benchmark job's scales. Also under
    `/jobs/{id}/artifacts/quality_speed.png`."""
    record = _require(store, job_id)
    path = storage.job(job_id) / QUALITY_SPEED_CHART
    if not path.is_file():
        raise ApiError(404, "no_chart", f"job {job_id!r} has no quality-vs-speed chart: benchmark jobs draw one "
                       f"when they succeed (this is a {record['kind']} job, {record['state']})")
    return FileResponse(path, media_type="image/png", filename=f"job-{job_id}-{QUALITY_SPEED_CHART}")


# ----------------------------------------------------------------------------------------- results

def _results_folder(store: JobStore, storage: Storage, job_id: str) -> tuple[dict[str, Any], FilePath]:
    record = _require(store, job_id)
    if record["kind"] != "infer":
        raise ApiError(404, "no_results", f"job {job_id!r} is a {record['kind']} job; only infer jobs have "
                       f"result frames")
    return record, storage.result(job_id)


def _frame_files(folder: FilePath) -> list[FilePath]:
    return sorted(p for p in folder.iterdir() if p.is_file() and _FRAME.match(p.name)) if folder.is_dir() else []


@router.get("/{job_id}/results", response_model=JobResults, summary="Output frames of an infer job",
            responses={404: _NOT_FOUND})
def job_results(job_id: JobId, store: StoreDep, storage: StorageDep) -> JobResults:
    """Frames appear as they are written; `complete` turns true when the job has succeeded."""
    record, folder = _results_folder(store, storage, job_id)
    sequences = []
    for sequence in sorted(p for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []:
        frames = [{"frame": path.name, "frame_index": int(_FRAME.match(path.name).group(1)),
                   "bytes": path.stat().st_size, "url": f"/jobs/{job_id}/results/{sequence.name}/{path.name}"}
                  for path in _frame_files(sequence)]
        sequences.append({"name": sequence.name, "frames": frames})
    return JobResults(job_id=job_id, state=record["state"], complete=record["state"] == "succeeded",
                      zip_url=f"/jobs/{job_id}/results.zip", sequences=sequences)


@router.get("/{job_id}/results.zip", summary="Every output frame of an infer job as one zip (streamed)",
            response_class=StreamingResponse,
            responses={200: {"content": {"application/zip": {}}}, 404: _NOT_FOUND})
def job_results_zip(job_id: JobId, store: StoreDep, storage: StorageDep) -> StreamingResponse:
    _, folder = _results_folder(store, storage, job_id)
    files = [path for sequence in sorted(p for p in folder.iterdir() if p.is_dir()) for path in _frame_files(sequence)
             ] if folder.is_dir() else []
    if not files:
        raise ApiError(404, "no_results", f"job {job_id!r} has written no result frames yet")
    headers = {"Content-Disposition": f'attachment; filename="job-{job_id}-results.zip"'}
    return StreamingResponse(_zip_stream(folder, files), media_type="application/zip", headers=headers)


@router.get("/{job_id}/results/{sequence}/{frame}", summary="One output frame of an infer job (EXR)",
            response_class=FileResponse, responses={200: {"content": {EXR_TYPE: {}}}, 404: _NOT_FOUND})
def job_result_frame(job_id: JobId, store: StoreDep, storage: StorageDep,
                     sequence: SequenceName,
                     frame: Annotated[str, Path(description="frame file name or index", examples=["frame_0003.exr"],
                                                json_schema_extra={"pattern": _FRAME.pattern})]
                     ) -> FileResponse:
    _, folder = _results_folder(store, storage, job_id)
    match = _FRAME.fullmatch(frame)  # match would let "3\n" through: "$" passes a final newline
    try:
        sequence = checked_id(sequence, "sequence name")
    except ValueError as error:
        raise ApiError(404, "not_found", str(error)) from None
    path = folder / sequence / frame_file_name(int(match.group(1))) if match else None
    if path is None or not path.is_file():
        raise ApiError(404, "not_found", f"job {job_id!r} has no result frame {frame!r} of sequence {sequence!r}")
    return FileResponse(path, media_type=EXR_TYPE, filename=f"{sequence}_{path.name}")


class _Sink(io.RawIOBase):
    """A write-only stream whose bytes are taken out as they come: zipfile writes into it, the response reads."""

    def __init__(self) -> None:
        self._chunks: list[bytes] = []

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        self._chunks.append(bytes(data))
        return len(data)

    def take(self) -> bytes:
        data = b"".join(self._chunks)
        self._chunks.clear()
        return data


def _zip_stream(folder: FilePath, files: list[FilePath], chunk: int = 1 << 20) -> Iterator[bytes]:
    # Stored, not deflated: EXR frames are compressed already. zipfile writes to an unseekable stream with data
    # descriptors, so the archive is produced as it is sent, never held whole in memory.
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED) as archive:
        for path in files:
            with archive.open(str(path.relative_to(folder)), "w") as entry, path.open("rb") as source:
                while data := source.read(chunk):
                    entry.write(data)
                    yield sink.take()
            yield sink.take()
    yield sink.take()
