"""The ``tbsim`` command line: ``app`` parses and dispatches (``main`` is its entry point),
``commands`` holds one typed config per command (the single source of its options and
``--help``). ``python -m tbsim_env.cli`` runs it too."""

from tbsim_env.cli.app import main

__all__ = ["main"]
