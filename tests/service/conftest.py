"""Shared fixtures of the service tests: settings on a temporary data folder, apps, Redis db 15, tiny data.

- ``settings``: DENOISER_* environment pointed at ``tmp_path`` (data) and Redis db 15, caches cleared, so code
  that calls ``get_settings()`` / ``get_storage()`` directly sees the same values as the dependencies.
- ``make_app(*routers, public=(), **setting_changes)``: a small FastAPI app with only the given routers (behind
  the API-key dependency, ``public`` ones without it), the error handlers, and settings/storage overrides;
  for testing one resource while the others are not written or not wanted.
- ``app`` / ``client``: the full ``service.http.app.create_app()`` with the same overrides (lifespan run).
- ``redis_db``: a client on db 15, flushed before and after; skips the test when Redis is not running.
- ``tiny_frames`` / ``tiny_sequence`` / ``make_archive``: 8x8 frame bundles, sequence folders written with
  SequenceWriter, and zip / tar / tar.gz archives of folders.
- ``registry_settings`` / ``make_store``: the shared MLflow store with registered test models, and session stores
  on Redis db 15 (tests/service/session_fixtures.py, where the models and frames of the session tests live).
"""

from __future__ import annotations

import io
import os
import tarfile
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi import APIRouter, Depends, FastAPI
from fastapi.testclient import TestClient

from model.io.dataset import SequenceWriter
from model.io.frames import FrameBundle
from service.http.auth import require_api_key
from service.http.errors import install_error_handlers
from core.settings import Settings, get_settings
from core.storage import Storage, get_storage
from tests.builders import make_frame
from tests.service.session_fixtures import make_store, registry_settings

__all__ = ["make_store", "registry_settings"]  # fixtures of every test below tests/api

# DENOISER_TEST_REDIS_URL lets two checkouts run their suites side by side on separate databases.
TEST_REDIS_URL = os.environ.get("DENOISER_TEST_REDIS_URL", "redis://127.0.0.1:6379/15")


@pytest.fixture
def settings(tmp_path, monkeypatch) -> Iterator[Settings]:
    for name in list(os.environ):
        if name.startswith("DENOISER_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("DENOISER_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("DENOISER_REDIS_URL", TEST_REDIS_URL)
    get_settings.cache_clear()
    yield get_settings()
    get_settings.cache_clear()


@pytest.fixture
def storage(settings) -> Storage:
    return Storage(settings.data_dir).ensure()


def _override_dependencies(app: FastAPI, active: Settings) -> None:
    app.dependency_overrides[get_settings] = lambda: active
    app.dependency_overrides[get_storage] = lambda: Storage(active.data_dir).ensure()


@pytest.fixture
def make_app(settings) -> Callable[..., FastAPI]:
    def build(*routers: APIRouter, public: tuple[APIRouter, ...] = (), **setting_changes) -> FastAPI:
        active = settings.model_copy(update=setting_changes) if setting_changes else settings
        app = FastAPI()
        install_error_handlers(app)
        for router in public:
            app.include_router(router)
        for router in routers:
            app.include_router(router, dependencies=[Depends(require_api_key)])
        _override_dependencies(app, active)
        return app

    return build


@pytest.fixture
def app(settings) -> FastAPI:
    from service.http.app import create_app  # imported here: it needs every router module

    application = create_app()
    _override_dependencies(application, settings)
    return application


@pytest.fixture
def client(app) -> Iterator[TestClient]:
    with TestClient(app) as test_client:  # "with" runs the lifespan (session store)
        yield test_client


@pytest.fixture
def redis_db(settings):
    import redis

    client = redis.Redis.from_url(TEST_REDIS_URL, socket_connect_timeout=1, socket_timeout=5)
    try:
        client.ping()
    except redis.RedisError as error:
        pytest.skip(f"Redis is not running at {TEST_REDIS_URL}: {error}")
    client.flushdb()
    yield client
    client.flushdb()
    client.close()


# --- tiny data -------------------------------------------------------------------------------------------


def _tiny_frames(count: int, *, size: int = 8, scales: tuple[int, ...] = (1,), cuts: tuple[int, ...] = (0,),
                 sequence: str = "", seed: int = 0) -> list[FrameBundle]:
    frames = []
    for index in range(count):
        frame = make_frame(seed + index, size, size, scales=scales, frame_index=index)
        frame.sequence = sequence
        frame.camera_cut = index in cuts
        frames.append(frame)
    return frames


@pytest.fixture
def tiny_frames() -> Callable[..., list[FrameBundle]]:
    """``tiny_frames(count, size=8, scales=(1,), cuts=(0,), sequence="", seed=0)``: valid frames 0..count-1."""
    return _tiny_frames


@pytest.fixture
def tiny_sequence() -> Callable[..., Path]:
    """``tiny_sequence(folder, count=2, scene="cornell", **frame_options)``: a sequence folder named after
    ``folder.name``, written with SequenceWriter; returns the folder."""

    def write(folder: Path, count: int = 2, *, scene: str | None = "cornell", **frame_options) -> Path:
        with SequenceWriter(folder, folder.name, scene=scene) as writer:
            for frame in _tiny_frames(count, **frame_options):
                writer.add(frame)
        return folder

    return write


def _archive_bytes(folder: Path, kind: str, prefix: str = "") -> bytes:
    """Every file under ``folder`` as ``prefix + relative path``, in a zip, tar or tar.gz, as bytes."""
    files = sorted(path for path in folder.rglob("*") if path.is_file())
    buffer = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as bundle:
            for path in files:
                bundle.write(path, prefix + path.relative_to(folder).as_posix())
    else:
        with tarfile.open(fileobj=buffer, mode="w:gz" if kind == "tar.gz" else "w") as bundle:
            for path in files:
                bundle.add(path, prefix + path.relative_to(folder).as_posix())
    return buffer.getvalue()


@pytest.fixture
def make_archive() -> Callable[..., bytes]:
    """``make_archive(folder, kind="zip" | "tar" | "tar.gz", prefix="")``: the folder's files as archive bytes."""
    return lambda folder, kind="zip", prefix="": _archive_bytes(Path(folder), kind, prefix)
