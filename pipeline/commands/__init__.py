"""The ``run`` and ``stages`` subcommands of ``python -m pipeline`` (see :mod:`pipeline.cli`)."""
