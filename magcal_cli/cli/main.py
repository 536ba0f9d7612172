"""The `magcal` command group: every command module registered under one entry point."""

from __future__ import annotations

import sys
import warnings

import click

from magcal_cli import __version__
from magcal_cli.cli import apply, batch, check, diagnose, export, fit, fleet, inspect, simulate
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, output_lost

__all__ = ["cli", "main"]


@click.group(context_settings=CONTEXT, epilog=EXIT_CODES)
@click.version_option(__version__, "--version", prog_name="magcal", message="%(prog)s %(version)s")
@click.pass_context
def cli(ctx: click.Context) -> None:
    """Calibrate magnetometers jointly with an IMU from recorded logs (MCAP, ROS bags, ArduPilot, PX4)."""
    ctx.ensure_object(dict)


for command in (fit.fit, diagnose.diagnose_cmd, check.check_cmd, batch.batch_cmd, simulate.simulate, inspect.inspect_cmd,
                export.export_cmd, apply.apply_cmd, fleet.fleet_cmd):
    cli.add_command(command)


def main() -> None:
    """Console entry point. numpy's RuntimeWarnings on degenerate data stay off stderr, where an error is one
    line (the fuzz tests, which call `cli`, still see and fail on them). A success whose output the reader of a
    pipe dropped unread exits 1 (a closed pipe, spec/cli.md), as a write into the closed pipe does."""
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    try:
        cli(prog_name="magcal")
    except SystemExit as exc:
        if exc.code in (0, None) and output_lost():
            sys.exit(1)
        raise
