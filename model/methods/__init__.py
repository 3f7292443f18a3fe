"""Denoising methods, learned and baseline, all driven through `output, state = method.step(frame, state)`."""
