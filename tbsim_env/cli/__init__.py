"""The ``tbsim`` command line: ``main`` parses and dispatches, ``commands`` holds one typed
config per command (the single source of its options and ``--help``)."""
