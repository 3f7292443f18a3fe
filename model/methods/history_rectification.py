"""History rectification for the learned seed methods (WSKPN, AFN, JNDS, MUNet), as a run-time setting that
checkpoints record.

WSKPN's and AFN's temporal accumulation keeps a reprojected history wherever the geometry test passes, MUNet blends
its accumulated radiance by a predicted weight wherever that test passes, and JNDS blends its warped filtered lobes
wherever they stay in the image; so where a light moved the history the network reads still holds the old shading,
and the network, trained on few moving lights, filters it as it is. ``rectify_history`` clips the warped history to
the current frame's 1 spp neighbourhood first, as the ``rectified`` presets of ``accumulation`` and ``svgf`` do
(``model.ops.rectify.rectify_accumulated``; JNDS: each lobe against this frame's; MUNet: the accumulated radiance
against this frame's upscaled samples). The weights are unchanged: it runs on models trained without it, and
on the held-out recipes it gains most where lights move (docs/results/findings.md).

A checkpoint without the entry loads with it off, as it ran when it was saved.
"""

from __future__ import annotations

import torch

from model.ops.rectify import rectify_accumulated

__all__ = ["HISTORY_SETTINGS", "RECTIFY_KEY", "RectifiableHistory"]

RECTIFY_KEY = "history_rectification"  # state-dict entry: 1 = the warped history is clipped before it is used
# The run-time settings of this mixin's methods that shipping can set (name -> what a model without it lacks).
HISTORY_SETTINGS: dict[str, str] = {"rectify_history": "no accumulated history to rectify"}


class RectifiableHistory:
    """Mixin for a ``Method`` (listed before it) whose step reads a reprojected history of the frame's radiance: the
    setting, its state-dict buffer and the clip itself. ``_init_rectification`` belongs in ``__init__``."""

    def _init_rectification(self) -> None:
        self.register_buffer(RECTIFY_KEY, torch.tensor(0.0))
        self._rectify_history = False  # mirrored, so a step never reads a tensor to branch on it

    @property
    def rectify_history(self) -> bool:
        """Whether the reprojected history is clipped to the current frame's neighbourhood before it is used."""
        return self._rectify_history

    def set_rectify_history(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise ValueError(f"rectify_history must be true or false, got {value!r}")
        getattr(self, RECTIFY_KEY).fill_(float(value))
        self._rectify_history = value

    def run_time_settings(self) -> dict[str, bool]:
        return {"rectify_history": self._rectify_history}

    def rectified(self, history: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
        """``history`` clipped to ``current``'s neighbourhood when the setting is on, else as it is."""
        return rectify_accumulated(history, current) if self._rectify_history else history

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        if RECTIFY_KEY not in state_dict:  # saved before the setting existed: no clip, as it ran then
            state_dict = {**state_dict, RECTIFY_KEY: torch.tensor(0.0)}
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._rectify_history = bool(getattr(self, RECTIFY_KEY).item() > 0.5)
        return result
