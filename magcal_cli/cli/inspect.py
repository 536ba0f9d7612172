"""`magcal inspect`: the streams a log holds."""

from __future__ import annotations

from pathlib import Path

import click

from magcal_cli.cli import options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, verbosity


@click.command("inspect", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.as_json("Print one JSON document instead of the table.")
@options.fmt
@click.option("--receive-time", is_flag=True, help="ROS bags and MCAP: time samples by receive time, not header stamps.")
@verbosity
@click.pass_context
@handle_errors
def inspect_cmd(ctx: click.Context, log: Path, as_json: bool, fmt: str | None, receive_time: bool) -> None:
    """List the streams in LOG: id, kind, source, count, rate, start and end time, units."""
    from magcal_cli.readers.inspect import inspect_log, to_json, to_table

    rec = inspect_log(log, fmt, receive_time)
    click.echo(to_json(rec) if as_json else to_table(rec))
