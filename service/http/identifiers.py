"""The path parameters that name things, one Annotated type per kind of identifier, used by every route.

Each carries its rule in the OpenAPI document (pattern, maxLength) from the constant the server's own check uses
(core.names, core.registry.MAX_VERSION, service.sessions.store.SESSION_ID), so the schema and the check cannot
drift. The rules are written into the schema only (``json_schema_extra``), not enforced by FastAPI: a value outside
them keeps the answer it always had, from the route's own check, which names the problem (400 ``invalid_name`` for
a dataset id, 404 for an unknown job or session, 422 for a malformed version), where FastAPI would answer every
pattern violation alike with 422 ``invalid_request``.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Path

from core.names import (ALIAS_MAX_LENGTH, ALIAS_PATTERN, HEX_ID_PATTERN, ID_MAX_LENGTH, ID_PATTERN,
                        RESERVED_ALIAS_PATTERN)
from core.registry import MAX_VERSION, VERSION_PATTERN
from service.sessions.store import SESSION_ID

ID_SCHEMA = {"pattern": ID_PATTERN, "maxLength": ID_MAX_LENGTH}

DatasetId = Annotated[str, Path(description="dataset id", examples=["kitchens"], json_schema_extra=ID_SCHEMA)]
SequenceName = Annotated[str, Path(description="sequence name (its folder name)", examples=["kitchen_7"],
                                   json_schema_extra=ID_SCHEMA)]
ModelName = Annotated[str, Path(description="registered model name", examples=["jnds-xs-x2"],
                                json_schema_extra=ID_SCHEMA)]
VersionNumber = Annotated[str, Path(description=f"version number (1 to {MAX_VERSION})", examples=["2"],
                                    json_schema_extra={"pattern": VERSION_PATTERN})]
AliasName = Annotated[str, Path(description="alias name (letters, digits, '_' and '-'; not 'latest' nor v<number>)",
                                examples=["champion"],
                                json_schema_extra={"pattern": ALIAS_PATTERN, "maxLength": ALIAS_MAX_LENGTH,
                                                   "not": {"pattern": RESERVED_ALIAS_PATTERN}})]
JobId = Annotated[str, Path(description="job id", examples=["5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e"],
                            json_schema_extra={"pattern": HEX_ID_PATTERN})]
SessionId = Annotated[str, Path(description="session id", examples=["0f8fad5bd9cb469fa16570867728950e"],
                                json_schema_extra={"pattern": SESSION_ID.pattern})]
