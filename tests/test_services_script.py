"""scripts/services.sh starts Redis where DENOISER_REDIS_URL points, with append-only persistence."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def redis_plan(tmp_path: Path, url: str | None) -> tuple[str, str, list[str]]:
    environment = {k: v for k, v in os.environ.items() if not k.startswith("DENOISER_")}
    environment["DENOISER_DATA_DIR"] = str(tmp_path / "data")
    if url is not None:
        environment["DENOISER_REDIS_URL"] = url
    printed = subprocess.run(["bash", str(ROOT / "scripts" / "services.sh"), "redis-command"], env=environment,
                             capture_output=True, text=True, check=True).stdout.splitlines()
    host, port = printed[0].split()
    return host, port, printed[1].split()


@pytest.mark.parametrize(("url", "host", "port"), [(None, "127.0.0.1", "6379"),
                                                   ("redis://127.0.0.1:6390/3", "127.0.0.1", "6390"),
                                                   ("redis://:pass@localhost:6391", "localhost", "6391"),
                                                   ("redis://10.0.0.5/0", "10.0.0.5", "6379")])
def test_redis_is_checked_and_started_where_the_redis_url_points(tmp_path, url, host, port):
    found_host, found_port, command = redis_plan(tmp_path, url)
    assert (found_host, found_port) == (host, port)
    assert command[command.index("--port") + 1] == port


def test_the_local_redis_persists_to_an_append_only_file_in_the_data_folder(tmp_path):
    _, _, command = redis_plan(tmp_path, "redis://127.0.0.1:6390/3")
    assert command[command.index("--appendonly") + 1] == "yes"
    assert "--save" not in command or command[command.index("--save") + 1] != ""
    assert command[command.index("--dir") + 1] == str((tmp_path / "data" / "redis").resolve())
