"""Stored datasets as the API changes them (no HTTP here): uploads received (``receive``), archives unpacked
safely (``archives``), validated and committed (``ingest``, in other renderers' layouts: ``layouts``), frames
staged one by one (``staged``), and the stored datasets read and deleted (``catalog``).

Every upload is received into its own folder under ``staging/``, unpacked and validated there, and only then
moved into ``datasets/<id>`` with ``os.rename``, under the dataset's lock (``core.dataset_lock``). So a failed
upload leaves nothing behind. Errors are ``errors.UploadError`` subclasses; each maps to one HTTP status in
``service.http.routes.datasets``.
"""
