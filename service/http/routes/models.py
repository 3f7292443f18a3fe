"""/models: registered models (MLflow registry), their versions with tags and metrics, and aliases.

HTTP only: core.registry does the work; its errors get their status from service.http.errors (UnknownModelError 404,
ValueError, a malformed version or alias name, 422, RegistryUnavailable 503).
"""

from __future__ import annotations

from pathlib import Path as FilePath
from typing import Annotated

from fastapi import APIRouter, Depends, Response

from service.http.errors import documented_error, domain_errors
from service.http.identifiers import AliasName, ModelName, VersionNumber
from core.registry import (
    ModelVersionInfo,
    RegisteredModelInfo,
    Registry,
    registry_for,
)
from service.http.schemas.models import AliasIn, AliasOut, ModelDetail, ModelSummary, ModelVersionOut
from core.settings import Settings, get_settings

router = APIRouter(prefix="/models", tags=["models"])


def registry_dependency(settings: Annotated[Settings, Depends(get_settings)]) -> Registry:
    """The registry of the request's settings (tests override get_settings; one Registry per configuration)."""
    return registry_for(settings.resolved_tracking_uri(), FilePath(settings.data_dir))


RegistryDep = Annotated[Registry, Depends(registry_dependency)]


_NOT_FOUND = documented_error("no such model, version or alias", "not_found",
                              "version 9 of model 'jnds-xs-x2' does not exist")
_INVALID = documented_error("malformed version number or alias name", "invalid_request",
                            "alias 'v3' of model 'jnds-xs-x2': Version alias name 'v3' is reserved.")
_UNAVAILABLE = documented_error("the MLflow tracking store cannot be reached", "registry_unavailable",
                                "model registry error for registered models: connection refused")


def version_out(info: ModelVersionInfo) -> ModelVersionOut:
    return ModelVersionOut(name=info.name, version=info.version, run_id=info.run_id, created_at=info.created_at,
                           method=info.method, preset=info.preset, scale=info.scale, params=info.params,
                           flops_per_pixel=info.flops_per_pixel, metrics=info.metrics, tags=info.tags,
                           aliases=info.aliases, ref=f"models:/{info.name}/{info.version}")


def _summary(info: RegisteredModelInfo) -> ModelSummary:
    return ModelSummary(name=info.name, description=info.description, latest_version=info.latest_version,
                        aliases=info.aliases)


def _alias_out(name: str, alias: str, info: ModelVersionInfo) -> AliasOut:
    return AliasOut(name=name, alias=alias, version=info.version, model_version=version_out(info))


@router.get("", response_model=list[ModelSummary], summary="List registered models",
            responses={503: _UNAVAILABLE})
def list_models(registry: RegistryDep) -> list[ModelSummary]:
    with domain_errors():
        return [_summary(info) for info in registry.list_models()]


@router.get("/{name}", response_model=ModelDetail, summary="A registered model with all its versions",
            responses={404: _NOT_FOUND, 503: _UNAVAILABLE})
def get_model(name: ModelName, registry: RegistryDep) -> ModelDetail:
    """Versions oldest first, each with method, preset, scale, parameter count, FLOPs per pixel and the metrics
    recorded on it (validation PSNR from training, ms per frame from a benchmark, when known)."""
    with domain_errors():
        info = registry.get_model(name)
    return ModelDetail(**_summary(info).model_dump(), versions=[version_out(v) for v in info.versions])


@router.get("/{name}/versions/{version}", response_model=ModelVersionOut, summary="One version of a model",
            responses={404: _NOT_FOUND, 422: _INVALID, 503: _UNAVAILABLE})
def get_version(name: ModelName, version: VersionNumber, registry: RegistryDep) -> ModelVersionOut:
    with domain_errors():
        return version_out(registry.get_version(name, version))


@router.delete("/{name}/versions/{version}", status_code=204, summary="Delete one version of a model",
               responses={404: _NOT_FOUND, 422: _INVALID, 503: _UNAVAILABLE})
def delete_version(name: ModelName, version: VersionNumber, registry: RegistryDep) -> Response:
    """Also drops the aliases that pointed at it and its cached checkpoint. Sessions already open on it go on
    with the weights they loaded; new sessions and jobs answer 404 for it."""
    with domain_errors():
        registry.delete_version(name, version)
    return Response(status_code=204)


@router.delete("/{name}", status_code=204, summary="Delete a model with all its versions",
               responses={404: _NOT_FOUND, 503: _UNAVAILABLE})
def delete_model(name: ModelName, registry: RegistryDep) -> Response:
    """Every version, alias and cached checkpoint of the model; open sessions keep their loaded weights."""
    with domain_errors():
        registry.delete_model(name)
    return Response(status_code=204)


@router.put("/{name}/aliases/{alias}", response_model=AliasOut, summary="Point an alias at a version",
            responses={400: documented_error("the body is not JSON", "invalid_json",
                                             "the body is not valid JSON at character 10"),
                       415: documented_error("the body was not sent as application/json", "unsupported_media_type",
                                             "Content-Type text/plain is not accepted here; send the body as "
                                             "JSON with Content-Type application/json"),
                       404: _NOT_FOUND, 422: _INVALID, 503: _UNAVAILABLE})
def set_alias(name: ModelName, alias: AliasName, body: AliasIn, registry: RegistryDep) -> AliasOut:
    """Creates the alias or moves it. Sessions resolve an alias once, when they are created: moving it changes
    the model of new sessions only."""
    with domain_errors():
        return _alias_out(name, alias, registry.set_alias(name, alias, body.version))


@router.get("/{name}/aliases/{alias}", response_model=AliasOut, summary="The version an alias points at",
            responses={404: _NOT_FOUND, 503: _UNAVAILABLE})
def get_alias(name: ModelName, alias: AliasName, registry: RegistryDep) -> AliasOut:
    with domain_errors():
        return _alias_out(name, alias, registry.get_alias(name, alias))


@router.delete("/{name}/aliases/{alias}", status_code=204, summary="Remove an alias",
               responses={404: _NOT_FOUND, 503: _UNAVAILABLE})
def delete_alias(name: ModelName, alias: AliasName, registry: RegistryDep) -> Response:
    with domain_errors():
        registry.delete_alias(name, alias)
    return Response(status_code=204)
