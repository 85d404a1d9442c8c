"""Subcommands of the ``fieldbus`` CLI; see :mod:`fieldbus.cli`."""
