"""The REST API (FastAPI): app, routes, HTTP schemas, errors, auth, request limits and inference sessions."""
