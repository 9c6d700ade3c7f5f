"""``python -m tbsim_env.cli``: the ``tbsim`` command."""

from tbsim_env.cli.app import main

raise SystemExit(main())
