"""Bodies of /datasets (the domain's descriptions of stored sequences, splits and staged uploads; the routes return them)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from core.names import SPLITS


Split = Literal[SPLITS]


class SequenceInfo(BaseModel):
    """One stored sequence: a folder of frame bundle EXRs plus its manifest."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "name": "kitchen_0",
            "split": "train",
            "scene": "kitchen",
            "frames": 64,
            "width": 640,
            "height": 360,
            "scales": [1, 2],
            "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"],
            "camera_cuts": [0],
        }]
    })

    name: str
    split: Split
    scene: str | None = Field(description="scene recipe the sequence was rendered from, when known")
    frames: int = Field(description="number of frames; frame i has frame_index i")
    width: int = Field(description="render resolution, pixels")
    height: int
    scales: list[int] = Field(description="reference scales present (target = scale x render resolution)")
    buffers: list[str] = Field(description="buffers present in the frames (model.io.frames.BUFFERS names)")
    camera_cuts: list[int] = Field(description="frame indices that start after a camera cut")


class SplitSummary(BaseModel):
    """Per split totals, read from the manifests only."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"sequences": 3, "frames": 192, "scenes": ["kitchen", "sponza"], "resolutions": [[640, 360]],
                      "scales": [1, 2]}]
    })

    sequences: int
    frames: int
    scenes: list[str]
    resolutions: list[list[int]] = Field(description="distinct render resolutions as [width, height]")
    scales: list[int]


class DatasetSummary(BaseModel):
    """One entry of GET /datasets."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"id": "kitchens", "sequences": 4, "frames": 256, "scenes": ["kitchen", "sponza"],
                      "splits": {"train": 3, "validation": 1, "test": 0}}]
    })

    id: str
    sequences: int
    frames: int
    scenes: list[str]
    splits: dict[Split, int] = Field(description="number of sequences in each split")


class DatasetDetail(BaseModel):
    """GET /datasets/{id}: every sequence with its split, frames, buffers, resolution and scales."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "id": "kitchens",
            "frames": 64,
            "scenes": ["kitchen"],
            "splits": {
                "train": {"sequences": 1, "frames": 64, "scenes": ["kitchen"], "resolutions": [[640, 360]],
                          "scales": [1, 2]},
                "validation": {"sequences": 0, "frames": 0, "scenes": [], "resolutions": [], "scales": []},
                "test": {"sequences": 0, "frames": 0, "scenes": [], "resolutions": [], "scales": []},
            },
            "sequences": [{
                "name": "kitchen_0", "split": "train", "scene": "kitchen", "frames": 64, "width": 640,
                "height": 360, "scales": [1, 2],
                "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"], "camera_cuts": [0],
            }],
        }]
    })

    id: str
    frames: int = Field(description="frames over all sequences")
    scenes: list[str]
    splits: dict[Split, SplitSummary]
    sequences: list[SequenceInfo]


class StagedSequence(BaseModel):
    """A sequence being uploaded frame by frame; it joins the dataset on POST .../commit."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "dataset": "kitchens", "sequence": "kitchen_7", "split": "validation", "scene": "kitchen",
            "frames": 3, "next_frame_index": 3, "width": 640, "height": 360, "scales": [1, 2],
            "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"],
        }]
    })

    dataset: str
    sequence: str
    split: Split
    scene: str | None
    frames: int = Field(description="frames received so far")
    next_frame_index: int = Field(description="the frame_index the next upload must have")
    width: int
    height: int
    scales: list[int]
    buffers: list[str]
