"""scripts/services.sh starts Redis where DENOISER_REDIS_URL points, with append-only persistence, and warns when
the Redis it uses (one already there) keeps nothing across its restart."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import redis

from tests.builders import closed_port

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


@pytest.fixture
def redis_with(tmp_path):
    """``redis_with(*options)``: the URL of a redis-server of this test's own, started with those options."""
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed")
    started = []

    def start(*options: str) -> str:
        port = closed_port()
        started.append(subprocess.Popen(["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--dir",
                                         str(tmp_path), *options], stdout=subprocess.DEVNULL))
        client = redis.Redis(port=port)
        for _ in range(200):  # it starts in milliseconds
            try:
                client.ping()
                return f"redis://127.0.0.1:{port}/0"
            except redis.ConnectionError:
                time.sleep(0.05)
        raise RuntimeError("redis-server did not start")

    yield start
    for process in started:
        process.terminate()
        process.wait(30)


@pytest.mark.parametrize(("options", "said"), [
    (("--appendonly", "no", "--save", ""), "WARNING: Redis keeps no persistence"),
    (("--appendonly", "no", "--save", "3600 1"), "Redis persistence: rdb"),
    (("--appendonly", "yes", "--save", ""), "Redis persistence: aof"),
])
def test_services_says_when_the_redis_it_uses_keeps_nothing_across_a_restart(tmp_path, redis_with, options, said):
    environment = {k: v for k, v in os.environ.items() if not k.startswith("DENOISER_")}
    environment.update(DENOISER_DATA_DIR=str(tmp_path / "data"), DENOISER_REDIS_URL=redis_with(*options))
    result = subprocess.run(["bash", str(ROOT / "scripts" / "services.sh"), "redis-check"], env=environment,
                            capture_output=True, text=True, check=True)
    assert said in result.stdout + result.stderr
    assert ("WARNING" in result.stderr) == said.startswith("WARNING")
