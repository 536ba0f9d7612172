"""`magcal fleet DB`: every vehicle's compasses over time from a history store, with the changes found."""

from __future__ import annotations

from pathlib import Path

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, QualityGateError, handle_errors, say, verbosity

FLEET_EXIT = ("Exit codes: 0 success; 1 the store cannot be read; 2 usage error (a bad option, an -o file that "
              "exists without --force); 3 a compass is in a --fail-on state; 123 internal error (a bug).")
FAIL_STATES = ("changed", "settled", "new")


def _states(_: click.Context, __: click.Parameter, value: str | None) -> tuple[str, ...]:
    """--fail-on STATE[,STATE]: states of FAIL_STATES."""
    if value is None:
        return ()
    states = tuple(s.strip() for s in value.split(",") if s.strip())
    bad = [s for s in states if s not in FAIL_STATES]
    if bad or not states:
        msg = f"expected states among {', '.join(FAIL_STATES)} (comma-separated), got {value!r}"
        raise click.BadParameter(msg)
    return states


def _scale(_: click.Context, __: click.Parameter, value: float | None) -> float | None:
    """--std-scale: a finite number >= 1."""
    if value is not None and not (value >= 1.0 and value < float("inf")):
        msg = f"expected a number >= 1 (1: trust the reported std), got {value:g}"
        raise click.BadParameter(msg)
    return value


@click.command("fleet", context_settings=CONTEXT, epilog=FLEET_EXIT)
@click.argument("db", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@options.option("output", ": the HTML fleet report (one page: the vehicles' table and trend plots)")
@options.option("fail-on", callback=_states,
                help="Exit 3 when a compass is in one of these states (STATE[,STATE]): changed (a watched parameter alarmed at "
                     "its latest flight: 'a compass changed'), settled (changed earlier), new (one flight).")
@click.option("--std-scale", type=float, default=None, callback=_scale,
              help="Multiply every reported std by this factor instead of the fleet's observed flight-to-flight "
                   "inflation (1: trust the reported std).")
@options.as_json("Print one JSON document: every compass's state, changes and series.")
@options.force("Overwrite an existing -o report.")
@verbosity
@click.pass_context
@handle_errors
def fleet_cmd(ctx: click.Context, db: Path, out: Path | None, fail_on: tuple[str, ...],
              std_scale: float | None, as_json: bool, force: bool) -> None:
    """Every vehicle's compasses over time from the history store DB (magcal fit/batch --history DB).

    For each compass, the series of every parameter with its uncertainty; a two-sided CUSUM on the standardised
    steps of its hard iron, soft iron, orientation and interference finds changes (docs/fleet.md). The summary
    goes to stdout.
    """
    import json

    from magcal_cli.history import fleet as model
    from magcal_cli.history.store import load

    to_stdout = out is not None and str(out) == "-"
    if out is not None and not to_stdout:
        guards.refuse_existing((out,), force)
    fleet = model.build(load(db), scale=std_scale)
    summary = json.dumps(model.to_json(fleet), indent=2) + "\n" if as_json else model.text(fleet)
    if out is not None:
        from magcal_cli.writers.fleet import html

        page = html(fleet)
        if to_stdout:                               # the page is the result; the summary goes to stderr
            click.echo(page, nl=False)
            click.echo(summary, nl=False, err=True)
        else:
            from magcal_cli.atomic import write_text

            write_text(out, page)
            say(ctx, f"wrote {out}")
    if not to_stdout:
        click.echo(summary, nl=False)
    failed = [c for c in fleet.compasses if c.state in fail_on]
    if failed:
        names = ", ".join(f"{c.vehicle} {c.sensor}" for c in failed[:5]) + (", ..." if len(failed) > 5 else "")
        msg = f"fleet --fail-on: {len(failed)} compass{'es' * (len(failed) != 1)} {'/'.join(fail_on)} ({names})"
        raise QualityGateError(msg)
