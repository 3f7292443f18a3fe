"""Every CLI test runs against a data folder of its own: the commands find the data folder, registry and tracking
store through the settings (DENOISER_*), so without this a test would write into the checkout's var/."""

from __future__ import annotations

import pytest

from core.settings import get_settings


@pytest.fixture(autouse=True)
def own_data_folder(monkeypatch, tmp_path_factory):
    folder = tmp_path_factory.mktemp("denoiser-data")
    monkeypatch.setenv("DENOISER_DATA_DIR", str(folder))
    for name in ("DENOISER_TRACKING_URI", "DENOISER_PRETRAINED_DIR", "DENOISER_URL", "DENOISER_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    get_settings.cache_clear()  # read again, with this test's environment
    yield folder
    get_settings.cache_clear()  # nothing of it outlives the test
