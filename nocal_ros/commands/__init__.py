"""Subcommands of the ``nocal`` CLI; see :mod:`nocal_ros.cli`."""
