"""Request and response bodies of the API (pydantic v2), one module per resource.

Input and output models are separate classes; every model carries an example (``json_schema_extra``) so the
OpenAPI document shows a complete request or response for each endpoint. Job parameters are job
specifications shared with the workers: ``core.jobs.specs``.
"""
