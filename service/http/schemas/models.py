"""Bodies of /models: registered models, versions and aliases (the MLflow registry)."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from core.registry import VERSION_PATTERN


class ModelSummary(BaseModel):
    """One entry of GET /models: a registered model, its newest version and its aliases."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "description": "JNDS xs, 2x upscaling, trained on kitchens",
                      "latest_version": "3", "aliases": {"champion": "2"}}]
    })

    name: str
    description: str | None = Field(None, description="the registered model's description, if any")
    latest_version: str | None = Field(description="highest version number; null when no version is registered")
    aliases: dict[str, str] = Field(description="alias -> version it points at")


class ModelVersionOut(BaseModel):
    """One registered version: what it is (method, preset, scale, size) and what it measured."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "name": "jnds-xs-x2", "version": "2", "run_id": "b260b403e5dc4cffa4c56a75595a40cb",
            "created_at": "2026-11-22T06:30:57.715000Z", "method": "jnds", "preset": "xs", "scale": 2,
            "params": 16228, "flops_per_pixel": 13416.0,
            "metrics": {"validation_psnr": 31.42, "ms_per_frame": 4.8},
            "tags": {"method": "jnds", "preset": "xs", "scale": "2", "params": "16228",
                     "flops_per_pixel": "13416", "steps": "20000", "validation_psnr": "31.4200"},
            "aliases": ["champion"], "ref": "models:/jnds-xs-x2/2",
        }]
    })

    name: str
    version: str
    run_id: str | None = Field(description="the MLflow run that trained it")
    created_at: datetime | None
    method: str | None = Field(description="registry method name (tag 'method')")
    preset: str | None = Field(description="size preset (tag 'preset')")
    scale: int | None = Field(description="output / render resolution ratio (tag 'scale')")
    params: int | None = Field(description="number of parameters (tag 'params')")
    flops_per_pixel: float | None = Field(description="FLOPs per output pixel of one step (tag 'flops_per_pixel')")
    metrics: dict[str, float] = Field(
        description="measurements recorded on the version: validation_psnr, validation_ssim, ms_per_frame and "
                    "tags 'metric.<name>', when known")
    tags: dict[str, str] = Field(description="every tag of the version, as stored")
    aliases: list[str] = Field(description="aliases pointing at this version")
    ref: str = Field(description="model reference for jobs: models:/NAME/VERSION")


class ModelDetail(ModelSummary):
    """GET /models/{name}: the summary plus every version, oldest first."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "description": None, "latest_version": "2",
                      "aliases": {"champion": "2"},
                      "versions": [ModelVersionOut.model_config["json_schema_extra"]["examples"][0]]}]
    })

    versions: list[ModelVersionOut]


class AliasIn(BaseModel):
    """PUT /models/{name}/aliases/{alias}: the version the alias should point at."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"version": "3"}]})

    version: str = Field(pattern=VERSION_PATTERN, description="an existing version number of the model",
                         examples=["3"])


class AliasOut(BaseModel):
    """An alias and the version it points at."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "alias": "champion", "version": "2",
                      "model_version": ModelVersionOut.model_config["json_schema_extra"]["examples"][0]}]
    })

    name: str
    alias: str
    version: str
    model_version: ModelVersionOut
