"""``python -m elastic_jax`` is the ``elastic-jax`` command line (see :mod:`elastic_jax.cli`)."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
