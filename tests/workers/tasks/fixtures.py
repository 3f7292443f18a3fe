"""Fixtures of the job tests: a job store on Redis db 15 under a prefix of its own, a tmp data folder."""

from __future__ import annotations

import os
import uuid

import pytest
import redis

from core.settings import Settings
from core.storage import Storage
from core.job_store import JobStore

TEST_REDIS_URL = os.environ.get("DENOISER_TEST_REDIS_URL", "redis://127.0.0.1:6379/15")


def redis_client() -> redis.Redis:
    client = redis.Redis.from_url(TEST_REDIS_URL, decode_responses=True)
    try:
        client.ping()
    except redis.ConnectionError:
        pytest.skip(f"no Redis at {TEST_REDIS_URL}")
    return client


@pytest.fixture
def store():
    """A JobStore whose keys carry a prefix unique to the test; they are deleted afterwards."""
    client = redis_client()
    prefix = f"test-{uuid.uuid4().hex[:8]}:denoiser:"
    yield JobStore(client, prefix)
    for key in client.scan_iter(f"{prefix}*"):
        client.delete(key)


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(data_dir=tmp_path / "var", redis_url=TEST_REDIS_URL,
                    tracking_uri=f"sqlite:///{tmp_path / 'mlflow' / 'mlflow.db'}",
                    mlflow_ui_url="http://mlflow.test:5000")


@pytest.fixture
def storage(settings) -> Storage:
    return Storage(settings.data_dir).ensure()
