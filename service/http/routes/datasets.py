"""/datasets: upload (archive or frame by frame), list, inspect, delete.

HTTP only: request bodies are streamed to a staging file here, everything else is service.datasets, whose
UploadError subclasses get their status from service.http.errors. Validation and moving files run in the thread
pool so a large upload never blocks the event loop.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request, Response
from starlette.concurrency import run_in_threadpool

from model.layouts import BUILTIN_LAYOUTS, Layout
from service.datasets import archives, catalog, errors, ingest, receive, staged
from service.http.errors import ApiError, documented_error, domain_errors
from service.http.identifiers import ID_SCHEMA, DatasetId, SequenceName
from service.http.request_limits import upload_slots
from service.datasets.descriptions import DatasetDetail, DatasetSummary, Split, StagedSequence
from core.settings import Settings, get_settings
from core import dataset_lock
from core.storage import Storage, get_storage
from service.datasets.layouts import UploadNotes

router = APIRouter(prefix="/datasets", tags=["datasets"])

StorageDep = Annotated[Storage, Depends(get_storage)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

# Any of these may carry an archive; the bytes decide which kind it is.
ARCHIVE_TYPES = ("application/zip", "application/x-zip-compressed", "application/x-tar", "application/gzip",
                 "application/x-gzip", "application/x-gtar", "application/x-compressed-tar",
                 "application/octet-stream")
FRAME_TYPES = ("image/x-exr", "application/octet-stream")

LayoutName = Annotated[str | None, Query(
    description="how the uploaded EXRs map to the frame bundle: a built-in layout (denoiser, blender-cycles, "
                "generic); other than denoiser, an archive holds one folder per sequence with the renderer's frame "
                "EXRs and optionally references/ (as denoiser import reads them)", examples=["blender-cycles"])]

_BAD_UPLOAD = documented_error("not a valid archive or dataset (the message names the member or file)",
                               "missing_manifest", "sequence folder kitchen_7 has no manifest.json")
_NOT_FOUND = documented_error("no such dataset", "not_found", "dataset 'kitchens' does not exist")
_BAD_NAME = documented_error("the dataset id or sequence name is not a valid id", "invalid_name",
                             "dataset id '.hidden' is not a valid id: use letters, digits, '.', '_' and '-' (at most "
                             "128, not starting with a punctuation mark)")
_BUSY = documented_error("the server's limit of uploads in progress is reached (Retry-After)", "too_many_uploads",
                         "2 dataset uploads are in progress, the server's limit is 2: retry in a moment")
_STALLED = documented_error("the client paused longer than the body read timeout", "body_timeout",
                            "the request body stalled: nothing arrived for 30 s; send the whole body without pausing")
_TOO_LARGE = documented_error("upload larger than the configured limit", "payload_too_large",
                              "the upload is at least 2147483649 bytes; the limit is 2147483648 bytes")
_UNSUPPORTED = documented_error("Content-Type not accepted", "unsupported_media_type",
                                "Content-Type text/plain is not accepted; send application/zip, ...")


def _binary_body(types: tuple[str, ...], description: str) -> dict:
    schema = {"type": "string", "format": "binary"}
    return {"requestBody": {"required": True, "description": description,
                            "content": {kind: {"schema": schema} for kind in types}}}


def _check_content_type(request: Request, accepted: tuple[str, ...]) -> None:
    declared = request.headers.get("content-type")
    if declared is None:
        return  # raw bytes without a type: sniffed like application/octet-stream
    media_type = declared.split(";", 1)[0].strip().lower()
    if media_type not in accepted:
        raise ApiError(415, "unsupported_media_type", f"Content-Type {media_type} is not accepted here; send "
                                                      f"{', '.join(accepted)}", {"accepted": list(accepted)})


def _layout(name: str | None) -> Layout | None:
    if name is None:
        return None
    if name not in BUILTIN_LAYOUTS:
        raise errors.InvalidUpload("invalid_layout", f"layout: unknown layout {name!r}; built-in layouts are "
                                                     f"{', '.join(BUILTIN_LAYOUTS)} (for another, convert the frames "
                                                     f"with denoiser import --layout FILE first)")
    return BUILTIN_LAYOUTS[name]


def _note_headers(response: Response, notes: UploadNotes) -> None:
    """X-Ignored-Channels, X-Ignored-Files (files of a renderer's folders that are not frames, a renderer's own
    manifest.json among them) and X-Import-Warnings, when there is something to say (non-ASCII escaped)."""
    headers = {"X-Ignored-Channels": ", ".join(sorted(notes.ignored_channels)),
               "X-Ignored-Files": ", ".join(notes.ignored_files),
               "X-Import-Warnings": " | ".join(notes.warnings)}
    for key, value in headers.items():
        if value:
            response.headers[key] = value.encode("ascii", "backslashreplace").decode()


async def _receive_archive(request: Request, response: Response, storage: Storage, settings: Settings,
                           dataset_id: str, *, create: bool, split: str, replace: bool,
                           layout: str | None) -> DatasetDetail:
    _check_content_type(request, ARCHIVE_TYPES)
    notes = UploadNotes()
    with domain_errors():
        chosen = _layout(layout)
    with upload_slots(settings.max_concurrent_uploads).take(), domain_errors(), \
            dataset_lock.workspace(storage, "upload") as work:
        archive = work / "upload.bin"
        await receive.save_stream(request.stream(), archive, settings.max_upload_bytes, "upload",
                                  request.headers.get("content-length"))
        limit = archives.unpacked_limit(archive.stat().st_size, max_bytes=settings.max_unpacked_bytes,
                                        max_ratio=settings.max_archive_ratio,
                                        exempt_bytes=settings.archive_ratio_exempt_bytes)
        detail = await run_in_threadpool(
            ingest.ingest_archive, storage, archive, work, dataset_id, create=create, split=split,
            replace=replace, max_unpacked_bytes=limit, max_pixels=settings.max_frame_pixels, layout=chosen,
            notes=notes, max_decoded_bytes=settings.max_decoded_frame_bytes)
    _note_headers(response, notes)
    return detail


@router.post(
    "",
    status_code=201,
    response_model=DatasetDetail,
    summary="Upload a new dataset (zip, tar or tar.gz)",
    responses={400: _BAD_UPLOAD, 409: documented_error("the id is taken", "dataset_exists",
                                                       "dataset 'kitchens' already exists"),
               408: _STALLED, 413: _TOO_LARGE, 415: _UNSUPPORTED, 429: _BUSY},
    openapi_extra=_binary_body(ARCHIVE_TYPES, "an archive of sequence folders (each manifest.json + frame EXRs), "
                                              "or of a whole dataset folder (manifest.json with splits)"),
)
async def upload_dataset(
    request: Request,
    response: Response,
    storage: StorageDep,
    settings: SettingsDep,
    name: Annotated[str | None, Query(description="dataset id to use (must be free); default: a generated id",
                                      examples=["kitchens"], json_schema_extra=ID_SCHEMA)] = None,
    split: Annotated[Split, Query(description="split for sequences the archive gives none (sequence folders)")]
    = "train",
    layout: LayoutName = None,
) -> DatasetDetail:
    """The body is streamed to staging, unpacked (links, absolute paths and `..` refused), every frame is read
    and checked against its manifest, and only then is the dataset moved into place: a failure stores nothing."""
    with domain_errors():
        dataset_id = catalog.new_dataset_id(name)
        if catalog.dataset_exists(storage, dataset_id):  # fail before receiving the body
            raise errors.UploadConflict("dataset_exists", f"dataset {dataset_id!r} already exists; add sequences "
                                                          f"with POST /datasets/{dataset_id}/sequences",
                                        {"dataset": dataset_id})
    detail = await _receive_archive(request, response, storage, settings, dataset_id, create=True, split=split,
                                    replace=False, layout=layout)
    response.headers["Location"] = f"/datasets/{dataset_id}"
    return detail


@router.get("", response_model=list[DatasetSummary], summary="List datasets")
def list_datasets(storage: StorageDep) -> list[DatasetSummary]:
    return catalog.list_datasets(storage)


@router.get("/{dataset_id}", response_model=DatasetDetail, summary="Inspect a dataset",
            responses={400: _BAD_NAME, 404: _NOT_FOUND})
def get_dataset(dataset_id: DatasetId, storage: StorageDep) -> DatasetDetail:
    """Scenes, splits and every sequence with its split, frame count, buffers, resolution and scales."""
    with domain_errors():
        return catalog.describe_dataset(storage, dataset_id)


@router.delete("/{dataset_id}", status_code=204, summary="Delete a dataset",
               responses={400: _BAD_NAME, 404: _NOT_FOUND})
def delete_dataset(dataset_id: DatasetId, storage: StorageDep) -> Response:
    with domain_errors():
        catalog.delete_dataset(storage, dataset_id)
    return Response(status_code=204)


@router.post(
    "/{dataset_id}/sequences",
    status_code=201,
    response_model=DatasetDetail,
    summary="Add sequences to a dataset (zip, tar or tar.gz)",
    responses={400: _BAD_UPLOAD, 404: _NOT_FOUND,
               409: documented_error("a sequence name is taken", "sequence_exists",
                                     "dataset 'kitchens' already has sequence(s) kitchen_0; pass replace=true"),
               408: _STALLED, 413: _TOO_LARGE, 415: _UNSUPPORTED, 429: _BUSY},
    openapi_extra=_binary_body(ARCHIVE_TYPES, "an archive of sequence folders or of a dataset folder"),
)
async def add_sequences(
    dataset_id: DatasetId,
    request: Request,
    response: Response,
    storage: StorageDep,
    settings: SettingsDep,
    split: Annotated[Split, Query(description="split for sequences the archive gives none")] = "train",
    replace: Annotated[bool, Query(description="replace sequences that already exist instead of 409")] = False,
    layout: LayoutName = None,
) -> DatasetDetail:
    """Like POST /datasets, into an existing dataset: all of the archive's sequences are added, or none."""
    with domain_errors():
        if not catalog.dataset_exists(storage, dataset_id):
            raise errors.UnknownDataset("not_found", f"dataset {dataset_id!r} does not exist")
    detail = await _receive_archive(request, response, storage, settings, dataset_id, create=False, split=split,
                                    replace=replace, layout=layout)
    response.headers["Location"] = f"/datasets/{dataset_id}"
    return detail


@router.post(
    "/{dataset_id}/sequences/{sequence}/frames",
    response_model=StagedSequence,
    summary="Upload the next frame of a sequence (one frame bundle EXR)",
    responses={400: documented_error("not a valid frame bundle, or it does not match the first frame",
                                     "invalid_frame", "frame upload to kitchens/kitchen_7: buffer 'color': "
                                                      "2 pixels are not finite"),
               409: documented_error("frame_index is not the next one", "frame_out_of_order",
                                     "frame upload to kitchens/kitchen_7: frame_index is 5, expected 3"),
               408: _STALLED, 413: _TOO_LARGE, 415: _UNSUPPORTED, 429: _BUSY},
    openapi_extra=_binary_body(FRAME_TYPES, "one frame bundle EXR as written by model.io.exr.write_frame"),
)
async def upload_frame(
    dataset_id: DatasetId,
    sequence: SequenceName,
    request: Request,
    response: Response,
    storage: StorageDep,
    settings: SettingsDep,
    split: Annotated[Split | None, Query(description="split of the sequence (first frame; default train)")]
    = None,
    scene: Annotated[str | None, Query(description="scene name recorded in the manifest (first frame)")] = None,
    scales: Annotated[list[str] | None, Query(description="reference scales every frame must have, e.g. 1,2")]
    = None,
    layout: LayoutName = None,
) -> StagedSequence:
    """Frames must come in order from frame_index 0; the sequence is held in staging until
    POST .../commit moves it into the dataset (which is created then if it does not exist yet)."""
    _check_content_type(request, FRAME_TYPES)
    with domain_errors():
        catalog.checked_dataset_id(dataset_id)
        catalog.checked_sequence_name(sequence)
        expected_scales = _parse_scales(scales)
        chosen = _layout(layout)
        notes = UploadNotes()
        await run_in_threadpool(staged.expire_staged_uploads, storage, settings.staged_upload_ttl_seconds)
        with upload_slots(settings.max_concurrent_uploads).take(), dataset_lock.workspace(storage, "frame") as work:
            upload = work / "frame.exr"
            await receive.save_stream(request.stream(), upload, settings.max_frame_bytes, "frame",
                                      request.headers.get("content-length"))
            result = await run_in_threadpool(staged.stage_frame, storage, dataset_id, sequence, upload, split=split,
                                              scene=scene, scales=expected_scales, layout=chosen, notes=notes,
                                              max_pixels=settings.max_frame_pixels,
                                              max_decoded_bytes=settings.max_decoded_frame_bytes)
    _note_headers(response, notes)
    return result


def _parse_scales(values: list[str] | None) -> list[int] | None:
    if not values:
        return None
    scales = []
    for item in ",".join(values).split(","):
        item = item.strip()
        # ASCII digits only: str.isdigit() is also true for e.g. '²', which int() refuses (that was a 500).
        if not (item.isascii() and item.isdigit()) or int(item) < 1:
            raise errors.InvalidUpload("invalid_scales", f"scales: {item!r} is not a positive integer")
        scales.append(int(item))
    return scales


@router.get("/{dataset_id}/sequences/{sequence}/frames", response_model=StagedSequence,
            summary="State of a sequence being uploaded frame by frame",
            responses={400: _BAD_NAME, 404: documented_error("nothing staged", "not_found",
                                            "no frames of sequence 'kitchen_7' are staged for dataset 'kitchens'")})
def get_staged_sequence(dataset_id: DatasetId, sequence: SequenceName, storage: StorageDep) -> StagedSequence:
    """How many frames arrived and which frame_index comes next (to resume an interrupted upload)."""
    with domain_errors():
        return staged.staged_sequence(storage, dataset_id, sequence)


@router.delete("/{dataset_id}/sequences/{sequence}/frames", status_code=204,
               summary="Discard a sequence being uploaded frame by frame",
               responses={400: _BAD_NAME, 404: _NOT_FOUND})
def discard_staged_sequence(dataset_id: DatasetId, sequence: SequenceName, storage: StorageDep) -> Response:
    with domain_errors():
        staged.discard_staged_sequence(storage, dataset_id, sequence)
    return Response(status_code=204)


@router.post(
    "/{dataset_id}/sequences/{sequence}/commit",
    status_code=201,
    response_model=DatasetDetail,
    summary="Move a sequence uploaded frame by frame into the dataset",
    responses={400: _BAD_NAME, 404: documented_error("nothing staged", "not_found",
                                    "no frames of sequence 'kitchen_7' are staged for dataset 'kitchens'"),
               409: documented_error("the sequence name is taken", "sequence_exists",
                                     "dataset 'kitchens' already has sequence(s) kitchen_7; pass replace=true")},
)
def commit_sequence(
    dataset_id: DatasetId,
    sequence: SequenceName,
    response: Response,
    storage: StorageDep,
    replace: Annotated[bool, Query(description="replace a stored sequence of the same name instead of 409")]
    = False,
) -> DatasetDetail:
    with domain_errors():
        detail = staged.commit_staged_sequence(storage, dataset_id, sequence, replace=replace)
    response.headers["Location"] = f"/datasets/{dataset_id}"
    return detail
