"""Subcommands of the `denoiser` command line, one module per area."""
