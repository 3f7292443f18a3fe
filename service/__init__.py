"""The product's entry points: the `denoiser` command line (and, later, the FastAPI server)."""
