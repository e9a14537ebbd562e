"""``python -m elastic_jax.cli``: the same as the ``elastic-jax`` command."""

from . import main

raise SystemExit(main())
