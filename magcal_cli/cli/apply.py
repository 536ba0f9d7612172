"""`magcal apply`: a calibration applied to a log, the calibrated field over time as CSV, or the log copied with a
calibrated sensor_msgs/MagneticField topic (writers/roslog, docs/ros.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity

if TYPE_CHECKING:
    from magcal_cli.calibration.types import Calibration


@click.command("apply", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.option("output", required=True,
                help="What to write, by its name: OUT.mcap, OUT.bag or a new folder (a ROS 2 bag): a copy of the log "
                     "with a calibrated sensor_msgs/MagneticField topic per magnetometer (from a DataFlash, ULog or "
                     "CSV log: a ROS 2 MCAP file of its IMU and magnetometers); any other name: CSV of t [s], id, the "
                     "calibrated field x, y, z and its magnitude ('-': standard output).")
@click.option("--topic", default=None, metavar="TOPIC",
              help="The calibrated topic's name in a log output [default: <magnetometer topic>/calibrated].")
@click.option("--replace", is_flag=True,
              help="In a log output, write the calibrated field in place of the magnetometer's topic.")
@options.mag("apply")
@options.window("the log (the rows of the output)")
@options.fmt
@options.force("Overwrite an existing output.")
@verbosity
@click.pass_context
@handle_errors
def apply_cmd(ctx: click.Context, calibration: Path, log: Path, out: Path, topic: str | None, replace: bool,
              mags: tuple[str, ...], start_s: float | None, end_s: float | None, fmt: str | None, force: bool) -> None:
    """Apply CALIBRATION to LOG: the calibrated field over time as CSV, or LOG copied with a calibrated topic."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.calibration.apply import apply_to_recording
    from magcal_cli.readers import open_recording

    cal = guards.calibration_document(calibration, "CALIBRATION", "The arguments look swapped; run: magcal "
                                      "apply CAL.json LOG -o OUT.csv")
    guards.mags_in(mags, [m.id for m in cal.magnetometers], f"the calibration {calibration}")
    guards.time_window(start_s, end_s)
    stdout = guards.is_stdout(out)
    from magcal_cli.writers.roslog import output_kind

    if output_kind(out) is not None:
        _apply_to_log(ctx, cal, log, out, topic, replace, list(mags) or None, (start_s, end_s), fmt, force)
        return
    if topic or replace:
        msg = f"{out}: --topic and --replace name a topic of a log output; use -o OUT.mcap, OUT.bag or a folder"
        raise click.UsageError(msg)
    if not stdout:
        guards.refuse_existing((out,), force, ", or choose another -o")
        check_writable(out.parent, hint="Choose another -o")
    rec = guards.windowed(open_recording(log, fmt), start_s, end_s)
    if rec.cut is not None:
        say(ctx, f"warning: {rec.cut.message}")
    text, notes = apply_to_recording(cal, rec, list(mags) or None)
    for n in notes:
        say(ctx, n)
    if stdout:
        click.echo(text, nl=False)
        return
    write_text(out, text)
    click.echo(f"wrote {out}")


def _apply_to_log(ctx: click.Context, cal: Calibration, log: Path, out: Path, topic: str | None, replace: bool,
                  mags: list[str] | None, window: tuple[float | None, float | None], fmt: str | None,
                  force: bool) -> None:
    """`-o OUT.mcap|OUT.bag|DIR`: the log copied with the calibrated topics (writers.roslog.apply_to_log)."""
    from magcal_cli.atomic import check_writable
    from magcal_cli.readers import open_recording
    from magcal_cli.writers.roslog import apply_to_log

    if topic and replace:
        msg = "--topic and --replace: give one (--replace keeps the magnetometer's own topic name)"
        raise click.UsageError(msg)
    guards.refuse_existing((out,), force, ", or choose another -o")
    check_writable(out.parent, hint="Choose another -o")
    rec = guards.windowed(open_recording(log, fmt), *window)
    if rec.cut is not None:
        say(ctx, f"warning: {rec.cut.message}")
    done = apply_to_log(cal, log, out, topic, replace, mags=mags, rec=rec)
    for n in done.notes:
        say(ctx, n)
    click.echo(f"wrote {out} (" + ", ".join(f"{t}: {n} messages" for t, n in done.topics.items()) + ")")
