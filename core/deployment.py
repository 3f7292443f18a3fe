"""Whether the API may listen where it is asked to: beyond localhost (or with DENOISER_REQUIRE_API_KEY) only with a
real API key. Checked by ``denoiser serve`` before it starts uvicorn and by the app at startup."""

from __future__ import annotations

import ipaddress

from core.settings import Settings

# Keys that example files and tutorials use: a server reachable from other machines must not accept them.
PLACEHOLDER_KEYS = frozenset({"change-me", "changeme", "change_me", "secret", "password", "api-key", "apikey",
                              "your-api-key", "your-secret", "test", "example", "default", "denoiser", "admin"})


MIN_KEY_LENGTH = 16


LOOPBACK_NAMES = frozenset({"localhost", "ip6-localhost"})


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address to listen on) is reachable from this machine only."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a name other than localhost: assume it is reachable


def deployment_key_problem(api_key: str | None) -> str | None:
    """Why ``api_key`` cannot protect a server reachable from other machines, or None when it can."""
    if api_key is None or not api_key.strip():
        return "DENOISER_API_KEY is not set"
    if api_key.strip().lower() in PLACEHOLDER_KEYS:
        return f"DENOISER_API_KEY is the placeholder {api_key.strip()!r}"
    if len(api_key) < MIN_KEY_LENGTH:
        return f"DENOISER_API_KEY has {len(api_key)} characters, fewer than {MIN_KEY_LENGTH}"
    return None


def check_deployment_key(settings: Settings, host: str | None = None) -> None:
    """RuntimeError when the API would listen beyond localhost (``host``, or settings.require_api_key, which
    docker-compose sets) without a real key."""
    exposed = settings.require_api_key or (host is not None and not is_loopback(host))
    problem = deployment_key_problem(settings.api_key) if exposed else None
    if problem is not None:
        where = f"on {host}" if host is not None and not is_loopback(host) else "with DENOISER_REQUIRE_API_KEY set"
        raise RuntimeError(f"refusing to serve {where}: {problem}; set it to a secret of your own of at least "
                           f"{MIN_KEY_LENGTH} characters (e.g. `openssl rand -hex 24`)")
