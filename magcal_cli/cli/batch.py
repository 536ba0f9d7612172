"""`magcal batch`: fit many logs in parallel, locally or on a Dask cluster."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import (
    CONTEXT,
    handle_errors,
    say,
    verbosity,
)

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling


BATCH_EXIT = ("Exit codes: 0 every log fitted (or up to date); 1 a log could not be fitted (each log's own exit code, "
              "as magcal fit would give it, is in the table and the JSON); 2 usage error (no log found, an output "
              "that exists without --force); 3 a log failed a --fail-on gate (and none failed otherwise); 123 "
              "internal error; 130 interrupted (Ctrl-C), nothing half-written left.")


@click.command("batch", context_settings=CONTEXT, epilog=BATCH_EXIT)
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...")
@options.option("outdir", required=True,
                help="Output folder: each log's outputs go to DIR/<log stem>/ (a longer unique name when stems "
                     "collide), with the batch.json status that makes a rerun skip it.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None,
              help="Local worker processes, one log at a time each [default: the number of cores].")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Fit on the Dask cluster at this scheduler (e.g. tcp://10.0.0.5:8786) instead of local processes; "
                   "the workers need the same paths and magcal with: pip install 'magcal-cli[fleet]'.")
@options.mag("calibrate in every log")
@options.option("method", ", as in magcal fit")
@options.option("effects", help="Physics beyond the base model, as in magcal fit (repeatable, comma-separated) "
                                 "[default: auto].")
@options.option("outputs", " of each log", default_text="as in magcal fit: json,yaml,report,html and the firmware "
                                                        "file of ArduPilot and PX4 logs")
@options.window("each log")
@options.option("fail-on", callback=options.fail_on("fit"),
                help="A log whose magnetometer meets a condition is 'gate failed' (its exit 3), as in magcal fit.")
@options.option("strict", help="Refuse cut logs instead of reading them up to their last record.")
@options.as_json("Print one JSON document with one entry per log.")
@options.force("Overwrite outputs that are not up to date (up-to-date logs are "
               "still skipped; remove DIR/<log>/batch.json to refit one).")
@options.option("history", ", by this process once the logs are fitted (on a Dask cluster too: the workers never "
                           "open it); logs skipped as up to date are recorded from their batch.json")
@options.option("vehicle", " every log")
@options.timing
@verbosity
@click.pass_context
@handle_errors
def batch_cmd(ctx: click.Context, inputs: tuple[str, ...], outdir: Path, jobs: int | None, scheduler: str | None,
              mags: tuple[str, ...], method: str, effects: tuple[str, ...], outputs: tuple[str, ...] | None,
              start_s: float | None, end_s: float | None, fail_on: tuple[Any, ...], strict: bool, as_json: bool,
              force: bool, history: Path | None, vehicle: str | None, imu_timing: Sampling | None,
              mag_timing: Sampling | None) -> None:
    """Fit many logs (files, folders searched recursively, globs) in parallel, locally or on a Dask cluster.

    Each log is fitted as 'magcal fit LOG -o DIR/<name>/' would; logs whose outputs are complete and newer than
    the log are skipped, and a failing log never stops the others. The summary goes to stdout.
    """
    import os
    import time

    from magcal_cli.batch.plan import BatchUsageError, FitOptions, discover, exit_code, plan
    from magcal_cli.batch.report import Runner, Tally, document, interrupted_line, table
    from magcal_cli.batch.run import Interrupted

    if jobs is not None and scheduler is not None:
        msg = "--jobs sets local processes; with --scheduler the cluster's workers fit the logs. Give one of them"
        raise click.UsageError(msg)
    if scheduler is not None:
        from magcal_cli.batch.dask import require_distributed

        require_distributed()                       # before any work: one line naming the extra to install
    guards.time_window(start_s, end_s)
    guards.method_effects(method, effects)
    guards.history(history, vehicle)
    opts = FitOptions(method, effects, outputs, mags, fail_on, strict, imu_timing, mag_timing, start_s, end_s,
                      history is not None, vehicle)
    try:
        work = plan(discover(list(inputs), outdir), outdir, opts, force)
    except BatchUsageError as exc:
        raise click.UsageError(str(exc)) from None
    workers = jobs or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    where = f"the Dask cluster at {scheduler}" if scheduler else f"{workers} local worker{'s' * (workers != 1)}"
    say(ctx, f"{len(work.order)} logs: {len(work.jobs)} to fit, {len(work.skipped)} up to date; fitting on {where}")
    tally = Tally(len(work.order))

    def done(r: Any) -> None:
        say(ctx, tally.line(r))
        if r.traceback and ctx.obj.get("verbose"):
            click.echo(r.traceback, err=True, nl=False)

    for r in work.skipped:
        done(r)
    start = time.perf_counter()
    try:                                            # Ctrl-C: the workers stopped within a second, nothing half-written
        if scheduler is not None:
            from magcal_cli.batch.dask import run_dask

            reports, seen = run_dask(work.jobs, scheduler, done)
            runner = Runner("dask", seen, scheduler)
        else:
            from magcal_cli.batch.run import run_local

            reports, runner = run_local(work.jobs, workers, done), Runner("local", workers)
    except Interrupted as stop:
        _record(ctx, history, [*work.skipped, *stop.reports])
        click.echo(f"Error: {interrupted_line([*work.skipped, *stop.reports], len(work.order))}", err=True)
        ctx.exit(130)
    wall = time.perf_counter() - start
    by_log = {r.log: r for r in (*work.skipped, *reports)}
    ordered = [by_log[log] for log in work.order if log in by_log]
    _record(ctx, history, ordered)
    click.echo(document(ordered, wall, runner, outdir) if as_json else table(ordered, wall, runner), nl=False)
    code = exit_code(ordered)
    if code:
        bad = [r for r in ordered if (r.exit_code not in (0, 3) if code == 1 else r.exit_code == 3)]
        click.echo(f"Error: batch: {len(bad)} of {len(ordered)} logs {'could not be fitted' if code == 1 else 'failed a --fail-on gate'}"
                   f" ({', '.join(r.name for r in bad[:5])}{', ...' if len(bad) > 5 else ''}). Their errors are in the "
                   f"summary and in {outdir}/<log>/batch.json", err=True)
        ctx.exit(code)


def _record(ctx: click.Context, history: Path | None, reports: list[Any]) -> None:
    """--history: every report's entries into the store in one transaction, by this process alone."""
    if history is None:
        return
    from magcal_cli.history.store import record

    made = [e for r in reports for e in r.history]
    added = record(history, made)
    say(ctx, f"history: {added} of {len(made)} results new in {history}")
