"""`magcal apply`: a calibration applied to a log, the calibrated field over time."""

from __future__ import annotations

from pathlib import Path

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity


@click.command("apply", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.option("output", required=True,
                help="CSV file to write: t [s], id, the calibrated field x, y, z and its magnitude ('-': standard "
                     "output).")
@options.mag("apply")
@options.window("the log (the rows of the output)")
@options.fmt
@options.force("Overwrite an existing output.")
@verbosity
@click.pass_context
@handle_errors
def apply_cmd(ctx: click.Context, calibration: Path, log: Path, out: Path, mags: tuple[str, ...],
              start_s: float | None, end_s: float | None, fmt: str | None, force: bool) -> None:
    """Apply CALIBRATION to LOG and write the calibrated field over time as CSV."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.calibration.apply import apply_to_recording
    from magcal_cli.readers import open_recording

    cal = guards.calibration_document(calibration, "CALIBRATION", "The arguments look swapped; run: magcal "
                                      "apply CAL.json LOG -o OUT.csv")
    guards.mags_in(mags, [m.id for m in cal.magnetometers], f"the calibration {calibration}")
    guards.time_window(start_s, end_s)
    stdout = guards.is_stdout(out)
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
