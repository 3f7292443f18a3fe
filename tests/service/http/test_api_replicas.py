"""Two API processes behind the real reverse proxy of docker-compose.yml (HAProxy, deploy/haproxy/denoiser.cfg): a
session's frames, over HTTP and over the WebSocket, go to one replica in order; when that replica is killed the
session continues on the other one from the Redis mirror, giving what one uninterrupted process gives.

The proxy runs the very file compose mounts, with only its server lines (between the two markers) and its listening
address replaced by the test's. Skipped with its reason where HAProxy is not installed (`scripts/install.sh
--proxy`) or Redis is not running.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from client.rest import DenoiserClient
from tests.builders import closed_port
from tests.service.conftest import TEST_REDIS_URL
from tests.service.session_fixtures import assert_same_image, stream_frames

ROOT = Path(__file__).resolve().parents[3]
PROXY_CONFIG = ROOT / "deploy" / "haproxy" / "denoiser.cfg"
SERVERS = re.compile(r"(    # replica servers begin\n).*?(    # replica servers end\n)", re.DOTALL)
REPLICA_HEADER = "X-Denoiser-Replica"
MODEL = "fused-fast-x1"  # a shipped model with a history (its fused temporal branch)
START_SECONDS = 180  # an API process imports torch and MLflow: slow on a loaded machine


def render_proxy_config(listen_port: int, replicas: dict[str, int]) -> str:
    """deploy/haproxy/denoiser.cfg with its replica servers and its listening address replaced, nothing else."""
    text = PROXY_CONFIG.read_text()
    assert SERVERS.search(text), "the server markers are missing from the proxy config"
    servers = "".join(f"    server {name} 127.0.0.1:{port} check\n" for name, port in replicas.items())
    text = SERVERS.sub(lambda match: match.group(1) + servers + match.group(2), text)
    text, count = re.subn(r"^    bind :8000$", f"    bind 127.0.0.1:{listen_port}", text, flags=re.MULTILINE)
    assert count == 1, "the proxy config no longer binds :8000"
    return text


def wait_until(condition, what: str, process: subprocess.Popen | None = None, log: Path | None = None,
               seconds: float = START_SECONDS) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        if process is not None and process.poll() is not None:
            pytest.fail(f"{what}: the process ended ({process.returncode}):\n{log.read_text()[-4000:] if log else ''}")
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {seconds} s\n{log.read_text()[-4000:] if log else ''}")
        time.sleep(0.1)


def answers(url: str) -> bool:
    try:
        return httpx.get(f"{url}/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


class Stack:
    """The processes of one test: API replicas and the proxy, each logging to a file, all stopped at the end."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self.processes: dict[str, subprocess.Popen] = {}
        self.ports: dict[str, int] = {}
        self.env = {name: value for name, value in os.environ.items() if not name.startswith("DENOISER_")}
        self.env.update(PYTHONPATH=str(ROOT), DENOISER_DATA_DIR=str(work / "data"), DENOISER_REDIS_URL=TEST_REDIS_URL,
                        # A float history continues exactly, so outputs after a failover equal the single run's.
                        DENOISER_SESSION_HISTORY_PRECISION="float",
                        DENOISER_SESSION_WORKERS="1", DENOISER_SESSION_THREADS="1")

    def log(self, name: str) -> Path:
        return self.work / f"{name}.log"

    def start(self, name: str, command: list[str]) -> subprocess.Popen:
        with self.log(name).open("ab") as log:  # appended: a restarted replica keeps its first run's log
            process = subprocess.Popen(command, cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                       start_new_session=True)
        self.processes[name] = process
        return process

    def start_api(self, name: str) -> str:
        """Start replica ``name``, on the port it had if it ran before (the proxy's server line names that port)."""
        port = self.ports.setdefault(name, closed_port())
        process = self.start(name, [sys.executable, "-m", "uvicorn", "service.http.app:app", "--host", "127.0.0.1",
                                    "--port", str(port), "--ws-max-size", "268435456"])
        url = f"http://127.0.0.1:{port}"
        wait_until(lambda: answers(url), f"API replica {name}", process, self.log(name))
        return url

    def start_proxy(self, binary: str) -> str:
        port = closed_port()
        config = self.work / "proxy.cfg"
        config.write_text(render_proxy_config(port, {name: self.ports[name] for name in ("api1", "api2")}))
        check = subprocess.run([binary, "-c", "-f", str(config)], capture_output=True, text=True)
        assert check.returncode == 0, check.stdout + check.stderr
        process = self.start("proxy", [binary, "-db", "-f", str(config)])
        url = f"http://127.0.0.1:{port}"
        wait_until(lambda: answers(url), "the proxy", process, self.log("proxy"))
        return url

    def kill(self, name: str) -> None:
        process = self.processes[name]
        os.killpg(process.pid, signal.SIGKILL)  # dies as a crashed container would: no shutdown, no last flush
        process.wait(30)

    def signal(self, name: str, number: int) -> None:
        os.killpg(self.processes[name].pid, number)

    def proxy_says(self, text: str) -> int:
        """How many log lines of the proxy begin with ``text`` (it logs each server going DOWN or UP; its warnings
        on stderr, which say the same after a prefix, are not counted)."""
        return len(re.findall(rf"^{re.escape(text)}", self.log("proxy").read_text(), re.MULTILINE))

    def stop(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGCONT)  # a replica the test froze
                os.killpg(process.pid, signal.SIGTERM)
        for process in self.processes.values():
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(30)


@pytest.fixture
def stack(tmp_path, redis_db):
    binary = shutil.which("haproxy") or next((path for path in ("/usr/sbin/haproxy",) if Path(path).exists()), None)
    if binary is None:
        pytest.skip("HAProxy is not installed (scripts/install.sh --proxy installs Debian's haproxy)")
    running = Stack(tmp_path)
    try:
        yield running, binary
    finally:
        running.stop()


def replica_of(client: DenoiserClient, session_id: str) -> str:
    return client.request("GET", f"/sessions/{session_id}").headers[REPLICA_HEADER]


def test_two_replicas_serve_a_sessions_frames_in_order_and_continue_it_after_one_is_killed(stack):
    running, binary = stack
    frames = stream_frames(17, seed=21)
    # Started one after the other: the first creates the shared data folder's registry database.
    direct = running.start_api("api1")
    with DenoiserClient(direct) as client:  # the uninterrupted single-process run
        single = client.create_session(MODEL)
        expected = [client.send_frame(single.id, frame)[0] for frame in frames]
        client.delete_session(single.id)
    running.start_api("api2")
    proxy = running.start_proxy(binary)

    with DenoiserClient(proxy) as client:
        # Paths without a session id are spread over the replicas.
        assert {client.request("GET", "/health").headers[REPLICA_HEADER] for _ in range(8)} == {"api1", "api2"}
        # Sessions land on both replicas by their ids; every request of one session on the same replica.
        sessions: dict[str, str] = {}
        for _ in range(40):
            session = client.create_session(MODEL)
            sessions.setdefault(replica_of(client, session.id), session.id)
            if len(sessions) == 2:
                break
        assert set(sessions) == {"api1", "api2"}, "40 sessions all hashed to one replica"
        for replica, session_id in sessions.items():
            for index in range(4):
                image, info = client.send_frame(session_id, frames[index])
                assert info.headers[REPLICA_HEADER] == replica
                assert (info.frame_index, info.history) == (index, "started" if index == 0 else "continued")
                assert_same_image(image, expected[index])
            with client.open_stream(session_id) as stream:  # the WebSocket goes through the proxy too
                for index in range(4, 7):
                    image, info = stream.send(frames[index])
                    assert (info.frame_index, info.history) == (index, "continued")
                    assert_same_image(image, expected[index])
            assert replica_of(client, session_id) == replica

        # The replica holding the first session dies once Redis holds its last frame (what a crash would lose
        # otherwise is the frame being answered: docs/operations.md).
        victim, survivor = "api1", "api2"
        session_id = sessions[victim]

        def mirrored() -> None:  # a switch of replica must not race the last frame's mirror
            wait_until(lambda: client.get_session(session_id).mirror.current, "the last frame's mirror", seconds=60)

        def send(index: int, replica: str) -> None:
            image, info = client.send_frame(session_id, frames[index])
            assert (info.headers[REPLICA_HEADER], info.frame_index, info.history) == (replica, index, "continued")
            assert_same_image(image, expected[index])

        mirrored()
        running.kill(victim)
        for index in range(7, 9):
            send(index, survivor)
        with client.open_stream(session_id) as stream:
            for index in range(9, 12):
                image, info = stream.send(frames[index])
                assert (info.frame_index, info.history) == (index, "continued")
                assert_same_image(image, expected[index])
        assert replica_of(client, session_id) == survivor
        assert client.get_session(session_id).frames_processed == 12
        # The survivor's own session went on where it was, untouched by the failover.
        image, info = client.send_frame(sessions[survivor], frames[7])
        assert (info.headers[REPLICA_HEADER], info.history) == (survivor, "continued")
        assert_same_image(image, expected[7])

        # The replica comes back (on its address): once its health check passes, its sessions return to it, and it
        # continues them from Redis.
        up = f"Server api/{victim} is UP"
        mirrored()
        running.start_api(victim)
        wait_until(lambda: running.proxy_says(up) == 1, f"the proxy taking {victim} back", seconds=60)
        for index in range(12, 14):
            send(index, victim)
        # Frozen rather than dead (cut off for a while, its memory kept): the proxy's checks take it out and the
        # other replica continues the session from Redis; thawed, it gets the session back with its memory copy
        # two frames behind Redis, which it must not step.
        mirrored()
        running.signal(victim, signal.SIGSTOP)
        wait_until(lambda: running.proxy_says(f"Server api/{victim} is DOWN") == 2, f"the proxy dropping {victim}",
                   seconds=60)
        for index in range(14, 16):
            send(index, survivor)
        mirrored()
        running.signal(victim, signal.SIGCONT)
        wait_until(lambda: running.proxy_says(up) == 2, f"the proxy taking {victim} back again", seconds=60)
        send(16, victim)
        assert client.get_session(session_id).frames_processed == 17
