"""The import rules between the layers (docs/architecture.md), read from the source with ``ast``.

Every import of every module counts, function-local ones included: a rule broken inside a function is broken
all the same. The one exception is written down in ``DEFERRED``. A failure names the file, the line and the import.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("model", "core", "service", "workers", "cli", "client")
OURS = set(PACKAGES)
# The service's serving domain (every package of service/ but http/) never imports its HTTP layer or FastAPI.
SERVICE_HTTP = "service.http"

# package -> imports it must not make (a name forbids the package and everything below it)
FORBIDDEN = {
    "model": OURS - {"model"},
    "core": {"service", "workers", "cli", "client", "celery", "kombu", "fastapi", "starlette", "uvicorn"},
    "service": {"workers", "cli"},
    "service-domain": {"workers", "cli", SERVICE_HTTP, "fastapi", "starlette", "uvicorn"},
    "workers": {"service", "cli", "fastapi", "starlette"},
    "cli": {"service", "workers"},
    "client": {"torch", "model", "core", "service", "workers", "cli", "mlflow"},
}
# Imports a layer may make inside a function only (never when the module is imported), with the reason.
DEFERRED = {
    # The client reads and writes frame bundles itself (client.frames) and owns the WebSocket's wire format
    # (client.codec, which the server imports). The one thing it borrows: streaming a renderer's folder over the
    # WebSocket in a layout other than denoiser reads the frames with the library's layout readers, which hold every
    # renderer's channel names and conventions once; model.layouts loads NumPy and OpenEXR, never torch (the
    # subprocess test below proves it). Frame bundles, arrays and the HTTP transport need no model import at all.
    ("client", "model.layouts"),
}
# What a forbidden package may still import, each with its reason.
ALLOWED = {
    # The client shares the job kinds, states and splits with everyone else: one plain-constants module.
    ("client", "core.names"),
    # Local training (`denoiser train --world-size N`) launches DDP ranks itself, as the worker does.
    ("cli", "workers.ddp"),
}
# What one module may import that the rest of its layer may not, with the reason.
MODULE_ALLOWED = {
    # The one Celery app: the API sends jobs through it and the workers run them, and those two never import each
    # other, so it lives in core. Its task modules are named by `include`, imported only by a starting worker.
    "core/celery_app.py": {"celery", "kombu"},
}


def imports_of(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """Every module ``path`` imports at run time (absolute names; relative imports resolved), with its line."""
    return sorted((line, name) for line, name, _ in _imports(path, root))


def _imports(path: Path, root: Path = ROOT) -> list[tuple[int, str, bool]]:
    """``imports_of`` with, for each import, whether it runs inside a function; ``if TYPE_CHECKING:`` imports,
    which never run, are left out."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    deferred, type_only = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            deferred |= {id(inner) for inner in ast.walk(node) if inner is not node}
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            type_only |= {id(inner) for inner in ast.walk(node) if inner is not node}  # never run
    found = []
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            names = [f"{base}.{alias.name}" if alias.name != "*" else base for alias in node.names]
        else:
            continue
        found += [(node.lineno, name, id(node) in deferred) for name in names]
    return found


def _listed(pairs: set[tuple[str, str]], layer: str, name: str) -> bool:
    return any(name == allowed or name.startswith(allowed + ".") for owner, allowed in pairs if owner == layer)


def breaks_rule(layer: str, name: str, in_function: bool = False, module: str | None = None) -> bool:
    """``module``: the importing file's path from the repository root (for ``MODULE_ALLOWED``)."""
    if _listed(ALLOWED, layer, name) or (in_function and _listed(DEFERRED, layer, name)):
        return False
    if any(name == allowed or name.startswith(allowed + ".") for allowed in MODULE_ALLOWED.get(module, ())):
        return False
    return any(name == banned or name.startswith(banned + ".") for banned in FORBIDDEN[layer])


def layer_of(path: Path, root: Path = ROOT) -> str:
    """The layer whose rules a module follows: its top-level package, or ``service-domain`` for service/ outside
    service/http/."""
    parts = path.relative_to(root).parts
    if parts[0] == "service" and (len(parts) < 3 or parts[1] != "http"):
        return "service-domain"
    return parts[0]


def violations() -> list[str]:
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            layer = layer_of(path)
            module = path.relative_to(ROOT).as_posix()
            for line, name, in_function in _imports(path):
                if breaks_rule(layer, name, in_function, module):
                    found.append(f"{path.relative_to(ROOT)}:{line}: {layer} imports {name}")
    return sorted(found)


def test_the_layers_import_only_what_they_may():
    assert violations() == []


def test_the_old_api_package_is_gone():
    assert not list(ROOT.glob("api/**/*.py"))  # the REST service is service/: its HTTP layer and its serving domain


def test_the_service_splits_into_its_http_layer_and_its_domain():
    assert layer_of(ROOT / "service" / "http" / "routes" / "sessions.py") == "service"
    assert layer_of(ROOT / "service" / "sessions" / "store.py") == "service-domain"
    assert layer_of(ROOT / "service" / "__init__.py") == "service-domain"


@pytest.mark.parametrize("layer, name, broken", [
    ("service", "workers.tasks.jobs", True),
    ("service", "service.sessions.store", False),
    ("service-domain", "service.http.errors", True),
    ("service-domain", "fastapi", True),
    ("service-domain", "service.datasets.catalog", False),
    ("service-domain", "core.registry", False),
    ("workers", "service.sessions.store", True),
    ("model", "client.codec", True),
    ("workers", "service.http.errors", True),
    ("core", "celery", True),
    ("core", "fastapi.responses", True),
    ("core", "service.http.schemas.jobs", True),
    ("model", "core.settings", True),
    ("client", "torch", True),
    ("client", "model.io.exr", True),
    ("client", "core.names", False),
    ("client", "numpy", False),
    ("client", "model.io.exr", True),
    ("client", "service.sessions.store", True),
    ("service-domain", "client.codec", False),
    ("cli", "workers.ddp", False),
    ("cli", "workers.tasks.jobs", True),
    ("service", "core.celery_app", False),
    ("service", "core.jobs.dispatch", False),
    ("workers", "core.job_store", False),
])
def test_the_rules_catch_what_they_should(layer, name, broken):
    assert breaks_rule(layer, name) == broken


def test_only_the_celery_app_module_of_core_imports_celery():
    assert not breaks_rule("core", "celery", module="core/celery_app.py")
    assert not breaks_rule("core", "kombu.Queue", module="core/celery_app.py")
    assert breaks_rule("core", "celery", module="core/registry.py")
    assert breaks_rule("core", "fastapi", module="core/celery_app.py")


def test_the_client_reads_a_renderers_layout_with_the_library_only_inside_a_function():
    assert breaks_rule("client", "model.layouts.read_layout_frame", in_function=False)
    assert not breaks_rule("client", "model.layouts.read_layout_frame", in_function=True)
    assert breaks_rule("client", "model.io.exr.read_frame", in_function=True)
    assert breaks_rule("client", "torch", in_function=True)


def test_the_layout_readers_the_client_borrows_never_load_torch():
    probe = ("import sys\n"
             "import model.layouts\n"
             "from client.stream import file_sender\n"
             "assert 'torch' not in sys.modules, sorted(m for m in sys.modules if m.startswith('torch'))[:5]\n")
    result = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_imports_are_read_everywhere_in_a_module(tmp_path):
    path = tmp_path / "service" / "http" / "routes" / "probe.py"
    path.parent.mkdir(parents=True)
    path.write_text("import os\n\ndef late():\n    from workers.tasks import jobs\n    from . import health\n"
                    "    from ..errors import ApiError\n")
    assert imports_of(path, tmp_path) == [(1, "os"), (4, "workers.tasks.jobs"), (5, "service.http.routes.health"),
                                          (6, "service.http.errors.ApiError")]


def test_the_api_process_never_loads_celery_tasks_and_the_client_never_loads_torch():
    probe = ("import sys\n"
             "class Block:\n"
             "    def find_spec(self, name, path=None, target=None):\n"
             "        if name.split('.')[0] in ('torch', 'model'):\n"
             "            raise ImportError(f'blocked: {name}')\n"
             "sys.meta_path.insert(0, Block())\n"
             "import client.rest, client.stream, client.frames, client.codec, client.answers\n"
             "sys.meta_path.pop(0)\n"
             "import service.http.app\n"
             "from service.http.dispatch import get_dispatcher\n"
             "get_dispatcher().celery.tasks\n"  # the Celery app built and finalized, as at the first job
             "loaded = sorted(m for m in sys.modules if m.startswith('workers'))\n"
             "assert not loaded, loaded\n")
    result = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]


def test_the_pyfunc_wrapper_imports_only_the_library_of_ours():
    # It travels inside each logged model with a copy of model/ and nothing else of ours (core.tracking).
    ours = [name for _, name in imports_of(ROOT / "core" / "pyfunc_model.py") if name.split(".")[0] in OURS]
    assert ours and all(name.split(".")[0] == "model" for name in ours), ours
