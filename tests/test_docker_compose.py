"""docker-compose.yml and the Dockerfile point at things that exist: images, commands, healthchecks, volumes.

Docker itself is not needed: the file is parsed with PyYAML and every command is resolved against the project
(console script, Celery app, ASGI app, MLflow CLI). Where a Docker Compose binary is on PATH, `config` also
validates the file against the Compose specification.
"""

from __future__ import annotations

import ast
import importlib.util
import re
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
PROJECT_IMAGE = "denoiser-service"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


@pytest.fixture(scope="module")
def services(compose) -> dict:
    return compose["services"]


def command_of(service: dict) -> list[str]:
    command = service.get("command")
    return command.split() if isinstance(command, str) else list(command or [])


def option(command: list[str], name: str) -> str | None:
    """The value of --name=VALUE or --name VALUE in a command."""
    for position, part in enumerate(command):
        if part.startswith(f"{name}="):
            return part.split("=", 1)[1]
        if part == name and position + 1 < len(command):
            return command[position + 1]
    return None


def test_the_expected_services_exist(services):
    assert set(services) == {"redis", "postgres", "mlflow", "api", "proxy", "worker", "worker-gpu"}


def test_every_service_has_an_image_or_an_existing_build_context(services):
    for name, service in services.items():
        assert "image" in service or "build" in service, name
        build = service.get("build")
        if build is None:
            continue
        context = ROOT / (build if isinstance(build, str) else build.get("context", "."))
        assert context.is_dir(), f"{name}: build context {context} does not exist"
        dockerfile = context / ("Dockerfile" if isinstance(build, str) else build.get("dockerfile", "Dockerfile"))
        assert dockerfile.is_file(), f"{name}: {dockerfile} does not exist"
        assert service.get("image", "").startswith(PROJECT_IMAGE), f"{name}: built images are tagged {PROJECT_IMAGE}"


def test_third_party_images_are_pinned_to_a_major_version(services):
    for name, image_name in (("redis", "redis"), ("postgres", "postgres"), ("proxy", "haproxy")):
        image = services[name]["image"]
        assert re.fullmatch(rf"{image_name}:\d+(\.\d+)*", image), f"{name}: {image!r} should pin a version"


def test_uvicorn_target_exists(services):
    command = command_of(services["api"])
    assert command[0] == "uvicorn"
    module, attribute = command[1].split(":")
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin, f"{module} is not importable"
    # Read rather than import: the app module pulls in every route.
    tree = ast.parse(Path(spec.origin).read_text())
    assigned = {target.id for node in tree.body if isinstance(node, ast.Assign) for target in node.targets
                if isinstance(target, ast.Name)}
    assert attribute in assigned, f"{module} defines no module-level {attribute!r}"
    assert option(command, "--host") == "0.0.0.0"
    # The replicas are reached through the proxy only, on the port uvicorn listens on.
    port = option(command, "--port")
    assert f" api:{port} " in proxy_servers(PROXY_CONFIG.read_text())


PROXY_CONFIG = ROOT / "deploy" / "haproxy" / "denoiser.cfg"


def proxy_servers(config: str) -> str:
    """The server lines between the markers of the proxy config (what the replicas test replaces)."""
    match = re.search(r"# replica servers begin\n(.*?)\s*# replica servers end", config, re.DOTALL)
    assert match, "the proxy config has no replica server markers"
    return match.group(1)


def test_the_api_scales_behind_the_proxy(compose, services):
    api, proxy = services["api"], services["proxy"]
    # `--scale api=N` needs replicas without a fixed host port or container name.
    assert "ports" not in api and "container_name" not in api
    assert proxy["ports"] == ["8000:8000"]
    assert proxy["depends_on"]["api"]["condition"] == "service_healthy"
    # The proxy runs the config file the replicas test runs.
    (mounted,) = proxy["configs"]
    assert mounted["target"] == "/usr/local/etc/haproxy/haproxy.cfg"
    assert (ROOT / compose["configs"][mounted["source"]]["file"]).resolve() == PROXY_CONFIG.resolve()
    config = PROXY_CONFIG.read_text()
    assert re.search(r"^    bind :8000$", config, re.MULTILINE)
    # Replicas come from Docker's DNS (the name of the api service), refreshed while the proxy runs.
    servers = proxy_servers(config)
    template = re.fullmatch(r"\s*server-template api (\d+) api:8000 check resolvers docker init-addr none.*", servers)
    assert template and int(template.group(1)) >= 3, servers
    assert re.search(r"^resolvers docker\n    nameserver dns 127\.0\.0\.11:53$", config, re.MULTILINE)
    assert "balance hash var(txn.session_id)" in config and "hash-type consistent" in config
    assert "option httpchk GET /health" in config  # the route open without the API key
    assert "option redispatch 1" in config


def test_the_proxy_hashes_exactly_the_paths_of_one_session():
    from service.sessions.store import SESSION_ID

    pattern = re.search(r"path_reg (\S+) }", PROXY_CONFIG.read_text()).group(1)
    assert pattern == r"^/sessions/[0-9a-f]{32}(/|$)"
    assert SESSION_ID.pattern == r"^[0-9a-f]{32}$"  # the ids the store makes, which the proxy's pattern spells out
    session = "0123456789abcdef" * 2
    for path in (f"/sessions/{session}", f"/sessions/{session}/frames", f"/sessions/{session}/stream",
                 f"/sessions/{session}/reset"):
        assert re.match(pattern, path) and path.split("/")[2] == session  # field(3,/): the hash key
    for path in ("/sessions", "/sessions/", f"/sessions/{session}x", "/health", f"/jobs/{session}"):
        assert not re.match(pattern, path), path


def test_celery_workers_use_the_project_app_with_the_solo_pool(services):
    from celery import Celery

    from core.names import QUEUES

    for name, queue in (("worker", "cpu"), ("worker-gpu", "gpu")):
        command = command_of(services[name])
        assert command[:2] == ["celery", "-A"] and command[3] == "worker", name
        module = importlib.import_module(command[2])
        assert isinstance(module.app, Celery), f"{command[2]} has no Celery app"
        assert option(command, "--pool") == "solo", f"{name}: DDP ranks need the non-daemonic solo pool"
        assert option(command, "--queues") == queue and queue in QUEUES


def test_mlflow_server_command(services):
    from mlflow.cli import cli

    command = command_of(services["mlflow"])
    assert command[:2] == ["mlflow", "server"] and "server" in cli.commands
    accepted = {opt for param in cli.commands["server"].params for opt in param.opts}
    for part in command[2:]:
        if part.startswith("--"):
            assert part.split("=", 1)[0] in accepted, f"mlflow server has no option {part}"
    backend = option(command, "--backend-store-uri")
    assert backend.startswith("postgresql://") and "@postgres:5432/" in backend
    assert "--serve-artifacts" in command
    assert option(command, "--artifacts-destination").startswith("/mlflow")
    # The API and workers reach the server as http://mlflow:5000: that Host header must be allowed.
    assert "mlflow:5000" in option(command, "--allowed-hosts").split(",")
    assert services["mlflow"]["image"].startswith(PROJECT_IMAGE)
    assert "psycopg2" in DOCKERFILE.read_text(), "the MLflow image needs psycopg2 for PostgreSQL"


def test_the_denoiser_console_script_and_its_serving_commands_exist():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["denoiser"] == "cli.main:main"
    from cli.main import build_parser

    commands = build_parser()._subparsers._group_actions[0].choices
    assert {"serve", "worker", "mlflow-ui"} <= set(commands)


def test_healthchecks(services):
    for name in ("redis", "postgres", "mlflow", "api"):  # the proxy checks the replicas itself
        test = services[name].get("healthcheck", {}).get("test")
        assert test and test[0] in ("CMD", "CMD-SHELL"), f"{name} has no healthcheck"
    assert "/health" in " ".join(services["api"]["healthcheck"]["test"])
    assert "/health" in " ".join(services["mlflow"]["healthcheck"]["test"])
    # Every service_healthy dependency points at a service that has a healthcheck.
    for name, service in services.items():
        for dependency, condition in (service.get("depends_on") or {}).items():
            assert dependency in services, f"{name} depends on unknown {dependency}"
            if condition.get("condition") == "service_healthy":
                assert "healthcheck" in services[dependency], f"{name} waits for {dependency}'s missing healthcheck"
    for name in ("api", "worker", "worker-gpu"):
        assert services[name]["depends_on"]["redis"]["condition"] == "service_healthy"
        assert services[name]["depends_on"]["mlflow"]["condition"] == "service_healthy"


def test_state_lives_on_named_declared_volumes(compose, services):
    declared = set(compose.get("volumes") or {})
    used = set()
    for name, service in services.items():
        for volume in service.get("volumes") or []:
            source = volume.split(":")[0] if isinstance(volume, str) else volume["source"]
            assert not source.startswith((".", "/")), f"{name}: {source} is a bind mount, not a named volume"
            assert source in declared, f"{name}: volume {source} is not declared"
            used.add(source)
    assert used == declared
    mounts = {name: {v.split(":")[0]: v.split(":")[1] for v in service.get("volumes") or []}
              for name, service in services.items()}
    assert mounts["redis"] == {"redis-data": "/data"}
    assert mounts["postgres"] == {"postgres-data": "/var/lib/postgresql/data"}
    assert "appendonly" in " ".join(command_of(services["redis"])), "queued jobs and sessions must survive restarts"
    artifacts = option(command_of(services["mlflow"]), "--artifacts-destination")
    assert artifacts.startswith(mounts["mlflow"]["mlflow-artifacts"])
    # The API and the workers share one data folder, at the path DENOISER_DATA_DIR names.
    for name in ("api", "worker", "worker-gpu"):
        assert mounts[name] == {"data": services[name]["environment"]["DENOISER_DATA_DIR"]}, name


def test_service_settings(services):
    from core.settings import Settings

    known = {f"DENOISER_{field.upper()}" for field in Settings.model_fields}
    for name in ("api", "worker", "worker-gpu"):
        environment = services[name]["environment"]
        assert {key for key in environment if key.startswith("DENOISER_")} <= known, name
        assert environment["DENOISER_TRACKING_URI"] == "http://mlflow:5000"
        assert environment["DENOISER_REDIS_URL"].startswith("redis://redis:6379/")
        assert re.fullmatch(r"\$\{DENOISER_API_KEY:\?[^}]+\}", environment["DENOISER_API_KEY"]), \
            "the API key comes from the environment, required (no default placeholder)"


def test_gpu_worker_is_in_the_gpu_profile_with_a_device_reservation(services):
    gpu = services["worker-gpu"]
    assert gpu["profiles"] == ["gpu"]
    devices = gpu["deploy"]["resources"]["reservations"]["devices"]
    assert any(d.get("driver") == "nvidia" and "gpu" in d.get("capabilities", []) for d in devices)
    # Its image has a CUDA build of torch: the CPU wheel index is switched off for it.
    assert gpu["build"]["args"]["TORCH_INDEX_URL"] == ""
    assert gpu["image"] != services["worker"]["image"]
    for name, service in services.items():
        if name != "worker-gpu":
            assert "gpu" not in (service.get("profiles") or []), f"{name} should run without the gpu profile"


def test_dockerfile_installs_the_project():
    text = DOCKERFILE.read_text()
    assert re.search(r"^FROM python:3\.11-slim", text, re.MULTILINE)
    assert re.search(r"apt-get install[^\n]*libllvm19", text), "Mitsuba's llvm backend needs libllvm19"
    assert "pyproject.toml" in text and "pip install --no-deps ." in text
    assert "ARG TORCH_INDEX_URL" in text
    pinned = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert "torch==2.13.0" in pinned  # the Dockerfile installs exactly what pyproject pins
    for arguments in re.findall(r"^COPY (.+)$", text, re.MULTILINE):
        for source in arguments.split()[:-1]:
            assert (ROOT / source).exists(), f"COPY {source}: not in the repository"
    ignored = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")]
    for needed in ("pyproject.toml", "README.md", "model", "core", "api", "workers", "cli", "client"):
        assert needed not in ignored, f".dockerignore leaves out {needed}, which the image needs"
    assert {".venv", ".git", "data"} <= set(ignored)


def _compose_binary() -> list[str] | None:
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True)
        if probe.returncode == 0:
            return ["docker", "compose"]
    standalone = shutil.which("docker-compose")
    if standalone:  # Compose v1 predates the Compose specification (top-level name, profiles): v2 only
        probe = subprocess.run([standalone, "version"], capture_output=True, text=True)
        if probe.returncode == 0 and re.search(r"\bv?2\.", probe.stdout):
            return [standalone]
    return None


def test_compose_config_validates_where_docker_compose_exists():
    binary = _compose_binary()
    if binary is None:
        pytest.skip("no Docker Compose binary on PATH")
    result = subprocess.run(binary + ["-f", str(COMPOSE), "--profile", "gpu", "config", "--quiet"],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr


def test_the_api_key_has_no_default_and_is_required(compose):
    environment = compose["x-denoiser-environment"]
    key = environment["DENOISER_API_KEY"]
    assert key.startswith("${DENOISER_API_KEY:?"), f"compose must refuse to start without a key, not default: {key}"
    assert environment["DENOISER_REQUIRE_API_KEY"] == "true"


def test_the_image_requires_a_real_api_key():
    assert "ENV DENOISER_REQUIRE_API_KEY=true" in DOCKERFILE.read_text()


def test_the_database_password_has_no_default_and_is_required():
    # Every use (postgres' own setting and MLflow's backend URI) must fail without it, none may fall back to a value.
    text = COMPOSE.read_text()
    uses = re.findall(r"\$\{POSTGRES_PASSWORD([^}]*)\}", text)
    assert len(uses) == 2, uses
    assert all(use.startswith(":?") for use in uses), f"compose must refuse to start without a password: {uses}"
