"""The argument parser: one subcommand per command, each adding its own arguments (the
``COMMAND`` record of its module) with its documented defaults."""

from __future__ import annotations

import argparse

from .. import __version__
from . import bench, demo, distances, fit_metric, geodesic, karcher, pca, shape_geodesic, shoot
from . import warmup as warmup_command
from .arguments import Command, DefaultsShown

# In the order ``elastic-jax --help`` lists them.
COMMANDS: tuple[Command, ...] = tuple(
    module.COMMAND
    for module in (
        geodesic,
        shape_geodesic,
        karcher,
        distances,
        fit_metric,
        pca,
        shoot,
        warmup_command,
        demo,
        bench,
    )
)


def build_parser() -> argparse.ArgumentParser:
    """The ``elastic-jax`` parser: ``--version`` and one subparser per :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="elastic-jax",
        description="Elastic shape analysis of spherical surfaces (split metrics, Su et al. 2020).",
        epilog="Exit codes: 0 ok, 2 bad input, 3 not converged, 130 interrupted, 143 terminated.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        p = sub.add_parser(
            command.name,
            help=command.help,
            description=command.description,
            formatter_class=DefaultsShown,
        )
        command.add_arguments(p)
    return parser
