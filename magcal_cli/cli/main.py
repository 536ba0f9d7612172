"""The `magcal` command group: every command module registered under one entry point."""

from __future__ import annotations

import atexit
import contextlib
import os
import sys
import warnings
from typing import NoReturn

import click

from magcal_cli import __version__
from magcal_cli.cli import apply, batch, check, diagnose, export, fit, fleet, inspect, simulate
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, INTERRUPTED, output_lost

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
        if exc.code == INTERRUPTED:
            _exit_interrupted()
        raise


def _exit_interrupted() -> NoReturn:
    """Exit 130 after a Ctrl-C that was handled. CPython remembers a KeyboardInterrupt that passed through exec() of
    a string (a dataclass being made while a module imports on first use) and, at the end of finalisation, kills
    the process with SIGINT instead: -2 for a caller that was promised 130 (about 1 run in 25 with the signal
    landing during the reader's import). The exit handlers run and the streams are flushed as at a normal exit;
    only the interpreter's own teardown is skipped."""
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(INTERRUPTED)
