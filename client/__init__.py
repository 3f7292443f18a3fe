"""The Python client of the REST API (``client.rest``): httpx only, importable without torch."""
