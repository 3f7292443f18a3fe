"""The MLflow ``pyfunc`` flavour of a trained method: a sequence of frame bundles in, the denoised RGB frames out.

Training logs every model this way (``core.tracking.MLflowTracker.log_model``), with the checkpoint inside, so a
registered version loads in a notebook, in any Python with the model's requirements (torch, numpy, MLflow), the
project installed or not::

    import mlflow
    model = mlflow.pyfunc.load_model("models:/fused-balanced-x1@pretrained")
    rgb = model.predict({"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion,
                         "jitter": jitter})          # (T, H * scale, W * scale, 3) float32

Input: one call is one sequence of T frames at render resolution H x W, channels last, as named arrays (the frame
bundle's buffers, ``model/io/frames.py``): ``color``, ``albedo``, ``normal`` (T, H, W, 3), ``depth`` (T, H, W, 1),
``motion`` (T, H, W, 2), ``jitter`` (T, 2). MLflow's tensor signatures have no optional inputs and drop names they
do not declare, so the optional buffers (``diffuse``, ``specular``, ``specular_albedo``, ``roughness``) and
``camera_cut`` reach the model only through ``model.unwrap_python_model().predict(None, inputs)``; without them
methods run as for a renderer that does not write them. The method steps through the frames in order with its
history carried from frame to frame (``method.step``), exactly as a session does; every call starts a new history.
Input values are repaired as in sessions (``model.io.sanitize``: NaN / Inf, out-of-range guides).

Self-contained: this file is logged as the model's code (MLflow's models-from-code: run at load, it names its
model with ``set_model``) and the library ``model/`` rides along as a code path; so it imports nothing else of ours.
"""

from __future__ import annotations

import numpy as np

import mlflow.models
import mlflow.pyfunc
from mlflow.models.signature import ModelSignature
from mlflow.types.schema import Schema, TensorSpec

REQUIRED = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2}  # buffer -> channels
OPTIONAL = {"diffuse": 3, "specular": 3, "specular_albedo": 3, "roughness": 1}
CHECKPOINT_KEY = "checkpoint"


def signature() -> ModelSignature:
    """Named float32 tensors in (the required buffers and the jitter), RGB out."""
    inputs = [TensorSpec(np.dtype(np.float32), (-1, -1, -1, channels), name)
              for name, channels in REQUIRED.items()]
    inputs.append(TensorSpec(np.dtype(np.float32), (-1, 2), "jitter"))
    return ModelSignature(inputs=Schema(inputs),
                          outputs=Schema([TensorSpec(np.dtype(np.float32), (-1, -1, -1, 3), "rgb")]))


def frames_of(inputs: dict[str, np.ndarray]):
    """The frames of one sequence as FrameBatch objects (N = 1), checking names and shapes."""
    import torch

    from model.methods.base import FrameBatch

    missing = [name for name in (*REQUIRED, "jitter") if name not in inputs]
    if missing:
        raise ValueError(f"missing inputs: {', '.join(missing)}; a sequence needs {', '.join((*REQUIRED, 'jitter'))}")
    frames = len(inputs["color"])
    for name, channels in {**REQUIRED, **OPTIONAL}.items():
        if name in inputs:
            shape = np.shape(inputs[name])
            if len(shape) != 4 or shape[0] != frames or shape[3] != channels:
                raise ValueError(f"input {name!r} has shape {shape}; expected (T={frames}, H, W, {channels})")
    if np.shape(inputs["jitter"]) != (frames, 2):
        raise ValueError(f"input 'jitter' has shape {np.shape(inputs['jitter'])}; expected ({frames}, 2)")
    cuts = np.asarray(inputs.get("camera_cut", np.zeros(frames, dtype=bool)), dtype=bool).reshape(-1)

    def planes(name: str, index: int) -> torch.Tensor | None:
        if name not in inputs:
            return None
        return torch.from_numpy(np.ascontiguousarray(np.asarray(inputs[name][index], dtype=np.float32))
                                ).permute(2, 0, 1).unsqueeze(0)

    for index in range(frames):
        yield FrameBatch(
            color=planes("color", index), albedo=planes("albedo", index), normal=planes("normal", index),
            depth=planes("depth", index), motion=planes("motion", index),
            jitter=torch.as_tensor(np.asarray(inputs["jitter"][index], dtype=np.float32)).view(1, 2),
            camera_cut=torch.tensor([bool(cuts[index])]), diffuse=planes("diffuse", index),
            specular=planes("specular", index), specular_albedo=planes("specular_albedo", index),
            roughness=planes("roughness", index))


def denoise_sequence(method, inputs: dict[str, np.ndarray]) -> np.ndarray:
    """Step ``method`` over the sequence, history carried; (T, H * scale, W * scale, 3) float32."""
    import torch

    from model.io.sanitize import sanitize_frame

    outputs, state = [], None
    with torch.no_grad():
        for frame in frames_of(inputs):
            frame, _ = sanitize_frame(frame)
            output, state = method.step(frame, state)
            outputs.append(output[0].permute(1, 2, 0).to(torch.float32).numpy())
    return np.stack(outputs)


class DenoiserModel(mlflow.pyfunc.PythonModel):
    """The checkpoint (artifact ``checkpoint``) as a pyfunc model; see the module notes for the input."""

    def load_context(self, context) -> None:
        from model.training.checkpoint import load_method

        self.method = load_method(context.artifacts[CHECKPOINT_KEY]).for_inference()

    # No type hints here: MLflow would read them as a second, conflicting signature.
    def predict(self, context, model_input, params=None):
        return denoise_sequence(self.method, model_input)


# Run as the logged model's code, this names the model MLflow loads (also harmless on a plain import).
mlflow.models.set_model(DenoiserModel())
