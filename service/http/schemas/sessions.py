"""Bodies of /sessions: streaming inference with server-side history."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from core.names import AUTO_MODEL


OnGap = Literal["reset", "reject"]


class SessionIn(BaseModel):
    """POST /sessions: which registered model to run (a version, an alias, or neither for the latest), or
    ``"model": "auto"`` with a constraint: the server chooses among registered versions by their tags."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={
        "examples": [{"model": "jnds-xs-x2", "alias": "champion", "on_gap": "reset"},
                     {"model": "jnds-xs-x2", "version": "3", "on_gap": "reject"},
                     {"model": "auto", "max_ms_per_frame": 20, "family": "wskpn"},
                     {"model": "auto", "min_psnr": 30},
                     {"model": "oidn:high"}, {"model": "svgf", "scale": 2}, {"model": "fused-balanced-x1"}]
    })

    model: str = Field(min_length=1, description="registered model name (GET /models), pretrained model name "
                                                 "(denoiser pretrained), a method without weights (oidn:high, "
                                                 "oidn-taa, svgf, accumulation), or 'auto': choose by "
                                                 "max_ms_per_frame / min_psnr", examples=["jnds-xs-x2"])
    version: str | None = Field(None, pattern=r"^[1-9][0-9]*$", description="version number; not with alias")
    alias: str | None = Field(None, min_length=1, description="alias, e.g. champion; not with version")
    on_gap: OnGap = Field("reset", description="a frame_index past the next expected one: 'reset' restarts the "
                                               "history (X-History: reset-gap), 'reject' answers 409 frame_gap")
    # model "auto" only (docs/service.md, "Choosing the model: auto"):
    max_ms_per_frame: float | None = Field(None, gt=0, allow_inf_nan=False,
                                           description="auto: the version's recorded ms_per_frame must be at most "
                                                       "this; alone, the best validation PSNR within it wins")
    min_psnr: float | None = Field(None, gt=0, allow_inf_nan=False,
                                   description="auto: validation PSNR (dB) at least this; the smallest such "
                                               "version wins (FLOPs per pixel)")
    family: str | None = Field(None, pattern=r"^[A-Za-z0-9_]+$", description="auto: only versions of this method")
    scale: Literal[1, 2] | None = Field(None, description="auto: only versions at this output scale; a method: its "
                                                        "output scale (default 1); a model: must be its own")
    layout: str | dict[str, Any] = Field(
        "denoiser", description="how the posted frames' EXR channels map to the frame bundle: a built-in layout "
                                "(denoiser, blender-cycles, generic) or a layout object (README, 'Bringing your "
                                "renderer's frames')", examples=["blender-cycles"])

    @field_validator("layout")
    @classmethod
    def _known_layout(cls, value: str | dict[str, Any]) -> str | dict[str, Any]:
        from model.layouts import LayoutError, layout_from_value

        try:
            layout_from_value(value)
        except LayoutError as error:
            raise ValueError(str(error)) from None
        return value

    @model_validator(mode="after")
    def _auto_fields(self) -> SessionIn:
        auto_fields = [name for name in ("max_ms_per_frame", "min_psnr", "family")
                       if getattr(self, name) is not None]
        if self.model == AUTO_MODEL:
            if self.version is not None or self.alias is not None:
                raise ValueError("model 'auto' chooses a version itself: give no version or alias")
            if self.max_ms_per_frame is None and self.min_psnr is None:
                raise ValueError("model 'auto' needs max_ms_per_frame, min_psnr or both")
        elif auto_fields:
            raise ValueError(f"{', '.join(auto_fields)} only go with model 'auto'")
        return self


class AutoChoiceOut(BaseModel):
    """How a session created with model 'auto' got its version: the constraint, the version's tags, and why."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "name": "wskpn-fit-x1", "version": "2", "method": "wskpn", "preset": "s", "scale": 1,
        "flops_per_pixel": 36260.0, "validation_psnr": 31.2, "ms_per_frame": 14.1,
        "ms_per_frame_resolution": "256x256", "constraint": {"max_ms_per_frame": 20, "family": "wskpn"},
        "candidates": 4,
        "reason": "wskpn-fit-x1 version 2 (wskpn:s at scale 1, 3.626e+04 FLOPs/px): the best validation PSNR "
                  "(31.20 dB) of the 2 of 4 candidate versions of family 'wskpn' within 20 ms per frame (14.1 ms "
                  "per frame at 256x256, 2 threads)"}]})

    name: str
    version: str
    method: str | None
    preset: str | None
    scale: int | None
    flops_per_pixel: float | None
    validation_psnr: float | None
    ms_per_frame: float | None
    ms_per_frame_resolution: str | None = Field(description="render resolution the ms_per_frame was timed at")
    constraint: dict[str, float | int | str] = Field(description="what the request asked for")
    candidates: int = Field(description="versions that had the tags to be compared")
    reason: str


class SessionModelOut(BaseModel):
    """The model version a session runs."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "version": "2", "alias": "champion", "method": "jnds", "preset": "xs",
                      "scale": 2, "params": 16228,
                      "buffers": ["color", "albedo", "diffuse", "specular", "normal", "depth", "roughness", "motion"]}]
    })

    name: str
    version: str | None = Field(description="registered: the version; pretrained: the weights' sha256 prefix; "
                                            "method: null")
    alias: str | None = Field(description="the alias the session was created with (resolved once, at creation)")
    method: str
    preset: str
    scale: int = Field(description="output / render resolution ratio")
    params: int = Field(description="number of parameters")
    source: Literal["registered", "pretrained", "method"] = Field(
        "registered", description="a registered model version, a pretrained model shipped with the service, or a "
                                  "method without weights")
    buffers: list[str] = Field(description="the render buffers the method reads: the required ones and the optional "
                                           "ones it uses; a stream client sends only these (others are ignored)")


class SessionMirrorOut(BaseModel):
    """Whether Redis holds the session's newest frame, i.e. what a restarted API would continue from."""

    current: bool = Field(description="Redis holds the session as it is now: a restart loses nothing")
    last_written_frame: int | None = Field(description="the last frame whose history Redis holds; null: none (a "
                                                       "new or reset session)")
    pending_since: datetime | None = Field(description="since when Redis has lacked the newest frame (a write "
                                                       "in progress, or failed and retried until it lands); null "
                                                       "while current")


class SessionOut(BaseModel):
    """A session: its model, its stream position and when it expires."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "id": "0f8fad5bd9cb469fa16570867728950e",
            "model": SessionModelOut.model_config["json_schema_extra"]["examples"][0],
            "created_at": "2026-11-22T06:30:57.715000Z", "last_used_at": "2026-11-22T06:31:02.100000Z",
            "expires_at": "2026-11-22T07:01:02.100000Z", "frames_processed": 42, "next_frame_index": 42,
            "on_gap": "reset", "resolution": [640, 360],
            "mirror": {"current": True, "last_written_frame": 41, "pending_since": None},
        }]
    })

    id: str
    model: SessionModelOut
    created_at: datetime
    last_used_at: datetime = Field(description="last creation, frame or reset")
    expires_at: datetime = Field(description="last_used_at + the server's session TTL")
    frames_processed: int = Field(description="frames run through the session since it was created")
    next_frame_index: int | None = Field(description="the frame_index that continues the history; null: no "
                                                     "history, any index starts one")
    on_gap: OnGap
    resolution: list[int] | None = Field(description="[width, height] every frame must have until a reset "
                                                      "(set by the first frame); null before it")
    choice: AutoChoiceOut | None = Field(None, description="model 'auto' only: the version chosen and why")
    layout: str | dict[str, Any] = Field("denoiser", description="the layout posted frames are read in")
    mirror: SessionMirrorOut | None = Field(None, description="the session's copy in Redis (the session store): "
                                                              "whether a restarted API continues it where it is")
    token: str | None = Field(None, description="only in the answer to POST /sessions, and only where the server "
                                                "has DENOISER_SESSION_OWNER_TOKENS on: send it as X-Session-Token "
                                                "with every request on this session")
