"""A small registered model, frames and fixtures for the /models and /sessions tests.

Creating an MLflow SQLite store costs seconds (table creation and migrations), so one store per test process
holds the registered model ``MODEL_NAME`` (a JNDS ``xs`` at scale 2 with seeded random weights: versions 1 and 2
with different weights, alias ``champion`` -> 1); tests that change aliases register their own model names with
``register_model``. Each test still gets its own data folder (so its own checkpoint cache) and its own Redis key
prefix in db 15.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
import uuid
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from model.training.checkpoint import save_checkpoint
from model.io.exr import encode_frame_exr
from model.io.frames import FrameBundle
from model.methods.base import Method, inference_outputs
from model.methods.registry import build_method
from service.http.routes import models as models_routes
from service.http.routes import session_stream
from service.http.routes import sessions as sessions_routes
from service.sessions.store import get_session_store
from tests.builders import synthetic_frame

MODEL_NAME = "jnds-xs-x2"
METHOD = "jnds:xs"
SCALE = 2
SIZE = 16  # render resolution of the test frames (output 32x32)


@dataclass(frozen=True)
class SharedRegistry:
    uri: str
    folder: Path
    checkpoints: dict[str, Path]  # version -> checkpoint file as saved before registration


def _method(seed: int) -> Method:
    torch.manual_seed(seed)
    return build_method(METHOD, scale=SCALE)


def _tags(method: Method, **extra: str) -> dict[str, str]:
    return {"method": method.name, "preset": method.preset, "scale": str(method.scale),
            "params": str(method.parameter_count()), "flops_per_pixel": "13416", **extra}


@lru_cache(maxsize=1)
def shared_registry() -> SharedRegistry:
    """The process's tracking store with MODEL_NAME versions 1 and 2 registered and alias champion -> 1."""
    from core.tracking import MLflowTracker

    folder = Path(tempfile.mkdtemp(prefix="denoiser-test-registry-"))
    atexit.register(shutil.rmtree, folder, True)
    uri = f"sqlite:///{folder / 'mlflow.db'}"
    tracker = MLflowTracker(uri, experiment="service-tests")
    tracker.start({"method": METHOD})
    checkpoints = {}
    for version, seed in (("1", 1), ("2", 2)):
        method = _method(seed)
        checkpoint = save_checkpoint(folder / f"v{version}.pt", method=method)
        extra = {"validation_psnr": "21.5000"} if version == "1" else {"ms_per_frame": "3.25", "metric.flip": "0.2"}
        registered = tracker.log_model(checkpoint, MODEL_NAME, _tags(method, **extra))
        assert registered["version"] == version
        checkpoints[version] = checkpoint
    tracker.finish("FINISHED")
    tracker.client.set_registered_model_alias(MODEL_NAME, "champion", "1")
    return SharedRegistry(uri=uri, folder=folder, checkpoints=checkpoints)


def register_model(name: str, versions: int = 1) -> None:
    """Register ``versions`` versions of a new model ``name`` in the shared store (for tests that change aliases)."""
    from core.tracking import MLflowTracker

    registry = shared_registry()
    tracker = MLflowTracker(registry.uri, experiment="service-tests")
    tracker.start({"method": METHOD})
    for _ in range(versions):
        tracker.log_model(registry.checkpoints["1"], name, _tags(_method(1)))
    tracker.finish("FINISHED")


def unique_name(prefix: str) -> str:
    return f"{prefix}-{uuid.uuid4().hex[:8]}"


# --- frames ----------------------------------------------------------------------------------------------


def stream_frames(count: int, *, size: int = SIZE, seed: int = 0, start: int = 0,
                  cuts: tuple[int, ...] = ()) -> list[FrameBundle]:
    """Valid frames with frame_index start..start+count-1 (references at scales 1 and 2, which sessions ignore)."""
    rng = np.random.default_rng(seed)
    return [synthetic_frame(rng, start + i, size, size, camera_cut=(start + i) in cuts) for i in range(count)]


def frame_bytes(frame: FrameBundle) -> bytes:
    return encode_frame_exr(frame)


def in_process_outputs(checkpoint: Path, frames: list[FrameBundle]) -> list[np.ndarray]:
    """What the checkpoint's method gives in process (``model.methods.base.inference_outputs``)."""
    from model.training.checkpoint import load_method

    return inference_outputs(load_method(checkpoint), frames)


def assert_same_image(actual: np.ndarray, expected: np.ndarray) -> None:
    assert actual.shape == expected.shape
    np.testing.assert_allclose(actual, expected, rtol=1e-5, atol=1e-6)


def assert_same_image_after_half_history(actual: np.ndarray, expected: np.ndarray) -> None:
    """After a restart from a float16 history (the default): its rounding, 2^-11 of each value, and not more."""
    assert actual.shape == expected.shape
    np.testing.assert_allclose(actual, expected, rtol=2e-3, atol=2e-4)


# --- fixtures --------------------------------------------------------------------------------------------


@pytest.fixture
def registry_settings(settings, monkeypatch):
    """The conftest settings (tmp data folder, Redis db 15) with the shared tracking store."""
    from core.settings import get_settings

    monkeypatch.setenv("DENOISER_TRACKING_URI", shared_registry().uri)
    get_settings.cache_clear()
    yield get_settings()
    get_settings.cache_clear()


@pytest.fixture
def make_store(registry_settings, redis_db):
    """``make_store(**setting_changes, clock=..., mirror_timing=...)``: a SessionStore on Redis db 15 under this test's own key prefix;
    every store of one test shares the prefix, so a second store plays the restarted API. It is built once the
    earlier stores' background mirror writes have landed, as after a clean shutdown."""
    from service.sessions.store import SessionStore

    prefix = f"denoiser:session:test-{uuid.uuid4().hex[:8]}:"
    stores = []

    def build(clock=None, mirror_timing=None, **changes):
        for earlier in stores:
            assert earlier.flush(timeout=30)
        active = registry_settings.model_copy(update=changes) if changes else registry_settings
        extra = {"clock": clock} if clock else {}
        if mirror_timing is not None:
            extra["mirror_timing"] = mirror_timing
        store = SessionStore(active, prefix=prefix, **extra)
        stores.append(store)
        return store

    yield build
    for store in stores:
        store.close()


class ManualTimers:
    """The mirror writers' (monotonic clock, timer starter) for a test that moves time itself: ``advance(s)`` moves
    the clock, ``fire()`` runs the timers started so far (as their delay being over would)."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.pending: list[tuple[float, object]] = []

    def monotonic(self) -> float:
        return self.now

    def start(self, delay: float, function):
        entry = (delay, function)
        self.pending.append(entry)
        timers = self

        class Handle:  # what the writer keeps, as it keeps a threading.Timer
            @staticmethod
            def cancel() -> None:
                if entry in timers.pending:
                    timers.pending.remove(entry)

        return Handle()

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def fire(self) -> int:
        due, self.pending = self.pending, []
        for _, function in due:
            function()
        return len(due)

    @property
    def timing(self):
        return self.monotonic, self.start


class FakeClock:
    """A clock tests move by hand (expiry without sleeping)."""

    def __init__(self, start: float = 1_800_000_000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


# --- the /sessions API -------------------------------------------------------------------------------------

@pytest.fixture
def api(make_app, make_store):
    """``api(store=None, clock=None, **setting_changes)`` -> (TestClient, store): /sessions (with its WebSocket,
    which checks the API key itself, as in service.http.app) and /models on a store of this test's Redis prefix (a second
    call without ``store`` plays a restarted API)."""

    def build(store=None, clock=None, **changes):
        store = store or make_store(clock=clock, **changes)
        app = make_app(sessions_routes.router, models_routes.router, public=(session_stream.router,),
                       tracking_uri=shared_registry().uri, **changes)
        app.dependency_overrides[get_session_store] = lambda: store
        return TestClient(app), store

    return build


def create(client: TestClient, **body) -> dict:
    response = client.post("/sessions", json={"model": MODEL_NAME, **body})
    assert response.status_code == 201, response.text
    assert response.headers["location"] == f"/sessions/{response.json()['id']}"
    return response.json()


def post_frame(client: TestClient, session_id: str, content, content_type: str | None = "image/x-exr"):
    headers = {"Content-Type": content_type} if content_type else {}
    if not isinstance(content, (bytes, bytearray)) and hasattr(content, "color"):
        content = frame_bytes(content)
    return client.post(f"/sessions/{session_id}/frames", content=content, headers=headers)
