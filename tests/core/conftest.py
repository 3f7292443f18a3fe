"""Fixtures of the core tests: the API tests' settings (temporary data folder, the test Redis database) and
registry_settings (those settings with the shared tracking store)."""

from tests.service.conftest import settings
from tests.service.session_fixtures import registry_settings

__all__ = ["registry_settings", "settings"]
