"""The ``denoiser`` command line (``cli.main``) and its subcommands (``cli.commands``)."""
