"""Right-sizing targets: what the chosen preset must achieve (``psnr=X``, ``flip=X``, ``ms=X[@WxH]``,
``within=D``), parsed from text; the rules behind each kind are in docs/fit.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from model.fit.choice import Rung

TARGET_KINDS = ("psnr", "flip", "ms", "within")
DEFAULT_TIMING_RESOLUTION = (256, 256)  # (width, height) of the render frames timed when the target is not ms


@dataclass(frozen=True)
class Target:
    """What the chosen preset must achieve (docs/fit.md); ``resolution`` (width, height) for ms."""

    kind: str
    value: float
    resolution: tuple[int, int] | None = None

    @classmethod
    def parse(cls, text: str, default_resolution: tuple[int, int] = DEFAULT_TIMING_RESOLUTION) -> Target:
        """``psnr=30``, ``flip=0.12``, ``ms=20@128x128`` (``ms=20``: at ``default_resolution``), ``within=0.2``."""
        forms = "psnr=DB, flip=ERROR, ms=MILLISECONDS[@WIDTHxHEIGHT] or within=DB"
        kind, sep, rest = str(text).strip().partition("=")
        kind = kind.strip().lower()
        if not sep or kind not in TARGET_KINDS:
            raise ValueError(f"target {text!r} is not one of {forms}")
        number, at, size = rest.partition("@")
        if at and kind != "ms":
            raise ValueError(f"target {text!r}: only an ms target takes @WIDTHxHEIGHT")
        try:
            value = float(number)
        except ValueError:
            raise ValueError(f"target {text!r}: {number.strip()!r} is not a number ({forms})") from None
        if not math.isfinite(value):
            raise ValueError(f"target {text!r}: the value must be finite")
        if kind in ("ms", "flip") and value <= 0:
            raise ValueError(f"target {text!r}: {kind} must be positive")
        if kind == "within" and value < 0:
            raise ValueError(f"target {text!r}: within takes a PSNR margin >= 0 dB")
        resolution = None
        if kind == "ms":
            resolution = parse_resolution(size) if at else tuple(default_resolution)
        return cls(kind, value, resolution)

    def __str__(self) -> str:
        value = f"{self.value:g}"
        if self.kind == "ms":
            return f"ms={value}@{self.resolution[0]}x{self.resolution[1]}"
        return f"{self.kind}={value}"

    def describe(self, bar: float | None = None) -> str:
        """In words, e.g. 'validation PSNR >= 30 dB'."""
        if self.kind == "psnr":
            return f"validation PSNR >= {self.value:g} dB"
        if self.kind == "flip":
            return f"validation FLIP <= {self.value:g}"
        if self.kind == "ms":
            return (f"<= {self.value:g} ms per frame at {self.resolution[0]}x{self.resolution[1]} (render), then "
                    f"the best validation PSNR")
        text = f"validation PSNR within {self.value:g} dB of the largest preset"
        return text + (f" (>= {bar:.2f} dB)" if bar is not None else "")

    def quality_met(self, rung: Rung, bar: float | None = None) -> bool | None:
        """Whether a measured rung meets a quality target (psnr, flip, within with its ``bar``); None: unknown."""
        if self.kind == "psnr":
            return None if rung.psnr is None else rung.psnr >= self.value
        if self.kind == "flip":
            return None if rung.flip is None else rung.flip <= self.value
        if self.kind == "within":
            return None if rung.psnr is None or bar is None else rung.psnr >= bar - 1e-9
        return None

    def within_budget(self, rung: Rung) -> bool | None:
        if self.kind != "ms":
            return None
        return None if rung.ms_per_frame is None else rung.ms_per_frame <= self.value


def parse_resolution(text: str) -> tuple[int, int]:
    """'128x128' or '128' -> (width, height)."""
    parts = str(text).strip().lower().split("x")
    try:
        values = [int(part) for part in parts]
    except ValueError:
        raise ValueError(f"resolution {text!r} is not WIDTHxHEIGHT (e.g. 128x128)") from None
    if len(values) == 1:
        values *= 2
    if len(values) != 2 or min(values) < 1 or max(values) > 8192:
        raise ValueError(f"resolution {text!r} is not WIDTHxHEIGHT with sides between 1 and 8192")
    return values[0], values[1]
