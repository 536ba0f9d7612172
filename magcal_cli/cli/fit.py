"""`magcal fit`: calibrate every selected magnetometer of a log and write the results."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import (
    CONTEXT,
    EXIT_CODES,
    QualityGateError,
    handle_errors,
    progress_line,
    say,
    verbosity,
    warning_lines,
)

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling


@click.command(context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.option("outdir", default_text="./<log stem>-magcal/")
@options.mag("calibrate")
@click.option("--imu", "imu", default=None, help="IMU stream id [default: the first with accelerometer and gyro].")
@options.option("method", "; auto picks the best one available for the log. attitude: against the vehicle's own "
                          "attitude estimate and the World Magnetic Model (flight logs with GPS)")
@options.option("outputs", default_text="json,yaml,report,html, and ardupilot for ArduPilot logs or px4 for "
                                         "PX4 ULogs", default=options.DEFAULT_OUTPUTS)
@options.window()
@options.fmt
@options.option("strict")
@options.alias("--allow-truncated", "allow_truncated", "a cut log is read up to its last complete record by "
               "default.", is_flag=True, expose_value=False)
@options.as_json("Print the calibration document on stdout.")
@options.force()
@click.option("--location", default=None, metavar="LAT,LON[,ALT]", callback=options.location,
              help="Where the log was recorded (deg, deg, m): dip and field strength from the World Magnetic Model "
                   "[default: the log's position stream, if any].")
@click.option("--date", default=None, metavar="YYYY-MM-DD", callback=options.wmm_date,
              help="Date for the World Magnetic Model [default: the log's date when known, else today].")
@click.option("--robust-loss", type=click.Choice(["l2", "huber", "cauchy"]), default="l2", show_default=True,
              help="Joint MAP (--method map): down-weight outlying readings with a Huber or Cauchy loss.")
@options.option("effects", default_text="auto")
@options.option("fail-on", callback=options.fail_on("fit"),
                help="Exit 3 when a magnetometer meets a condition, e.g. 'heading_std_deg>1,field_norm_rms_pct>2' "
                     "(METRIC OP NUMBER, comma-separated; see docs/firmware-export.md).")
@click.option("--export-worse", is_flag=True, default=False,
              help="Write a compass to the firmware parameter file even when its heading against the vehicle's "
                   "attitude is worse than the calibration it flew with [default: left out, with a warning].")
@options.option("history")
@options.option("vehicle", " the log")
@options.timing
@verbosity
@click.pass_context
@handle_errors
def fit(ctx: click.Context, log: Path, outdir: Path | None, mags: tuple[str, ...], imu: str | None, method: str,
        outputs: tuple[str, ...], start_s: float | None, end_s: float | None, fmt: str | None, strict: bool,
        as_json: bool, force: bool, location: tuple[float, float, float] | None, date: str | None,
        robust_loss: str, effects: tuple[str, ...], fail_on: tuple[Any, ...], history: Path | None,
        vehicle: str | None, imu_timing: Sampling | None, mag_timing: Sampling | None, export_worse: bool) -> None:
    """Calibrate every selected magnetometer of LOG against the IMU and write the results."""
    from magcal_cli.api import config
    from magcal_cli.calibration.document import dumps_json
    from magcal_cli.pipeline import calibrate
    from magcal_cli.writers import FIRMWARE_OUTPUTS

    guards.time_window(start_s, end_s)
    guards.history(history, vehicle)
    names = list(outputs)
    guards.method_effects(method, effects)
    auto = _firmware_output(ctx, log, fmt, names)
    outdir = outdir or Path.cwd() / f"{log.stem}-magcal"
    _check_outdir(outdir, names + ([auto] if auto else []), force)
    cfg = config(method=method, mag=mags or "all", imu=imu, start=start_s, end=end_s, strict=strict,
                 location=location, date=date, robust_loss=robust_loss,
                 effects="auto" if effects == options.AUTO else effects, imu_timing=imu_timing,
                 mag_timing=mag_timing, export_worse=export_worse)      # the Python API's Config, checked the same
    with progress_line(ctx) as progress:        # the writing too: its files are part of the run's time
        result = calibrate(log, cfg, fmt, progress)
        if auto and FIRMWARE_OUTPUTS.get(result.recording.format) == auto:
            names.append(auto)
        written = _write_fit_outputs(ctx, result, outdir, names, auto)
    if history is not None:
        _record(ctx, history, result, vehicle)
    if result.recording.cut is not None:
        say(ctx, f"warning: {result.recording.cut.message}")
    if as_json:
        click.echo(dumps_json(result.calibration), nl=False)
        _fit_gates(result, fail_on)
        return
    for m in result.calibration.magnetometers:
        q = m.quality
        click.echo(f"{m.id}: {m.method or result.calibration.method}, dip {m.dip_deg:.1f} deg, misalignment "
                   f"{_angle_deg(m.misalignment):.2f} deg, field-norm error {q.field_norm_rms_pct:.2f} % RMS, "
                   f"coverage {q.coverage_pct:.0f} %" if q else m.id)
    for r in result.calibration.refused:
        click.echo(f"{r['id']}: refused: {r['reason']}")
    lines = warning_lines(result.findings, [m.id for m in result.calibration.magnetometers]
                          + [r["id"] for r in result.calibration.refused], bool(ctx.obj.get("verbose")))
    for line in lines:
        say(ctx, f"warning: {line}")
    full = sum(f.severity.value == "warning" for f in result.findings)
    report = next((p for name in ("report.html", "report.txt") for p in written if p.name == name), None)
    if full > len(lines):
        say(ctx, f"{full} warnings in {len(lines)} kinds; the full text is in "
                     f"{report if report else 'the calibration document notes'} (-v prints it here)")
    for p in written:
        click.echo(f"wrote {p}")
    _fit_gates(result, fail_on)


def _record(ctx: click.Context, history: Path, result: Any, vehicle: str | None) -> None:
    """--history: the result's entries into the store (a log recorded before changes nothing)."""
    from magcal_cli.history.entry import entries
    from magcal_cli.history.store import record

    made = entries(result, vehicle)
    added = record(history, made)
    say(ctx, f"history: {added} of {len(made)} results new in {history}"
             + ("" if added == len(made) else " (the log was recorded before)"))


def _check_outdir(outdir: Path, names: list[str], force: bool) -> None:
    """Before the work: no output of `names` exists in `outdir` without --force (exit 2), and it is writable."""
    from magcal_cli.atomic import check_writable
    from magcal_cli.writers import check_targets, get_writer

    guards.refuse_existing((outdir / f for n in names for f in get_writer(n).files), force, ", or choose another -o")
    check_targets(outdir, names, force)
    check_writable(outdir, create=True, hint="Choose another -o")


def _write_fit_outputs(ctx: click.Context, result: Any, outdir: Path, names: list[str], auto: str | None
                       ) -> list[Path]:
    """fitrun.write_fit_outputs with its warnings on stderr (batch shares it), as lines of the progress renderer
    (they erase its live line first; -q silences them, as say does)."""
    from magcal_cli.progress import current
    from magcal_cli.writers.fitrun import write_fit_outputs

    return write_fit_outputs(result, outdir, names, auto, current())


def _firmware_output(ctx: click.Context, log: Path, fmt: str | None, names: list[str]) -> str | None:
    """The firmware output to add when --outputs was not given: ardupilot for DataFlash, px4 for ULog."""
    from magcal_cli.writers.fitrun import firmware_output

    if ctx.get_parameter_source("outputs") is not click.core.ParameterSource.DEFAULT:
        return None
    return firmware_output(log, fmt, names)


def _fit_gates(result: Any, conditions: tuple[Any, ...]) -> None:
    """Raise QualityGateError (exit 3) when a magnetometer meets a --fail-on condition."""
    from magcal_cli.writers.fitrun import gate_failures

    failed = gate_failures(result, conditions)
    if failed:
        msg = f"fit --fail-on: {'; '.join(failed)}"
        raise QualityGateError(msg)


def _angle_deg(rot: Any) -> float:
    """Rotation angle in degrees."""
    import numpy as np

    from magcal_cli import so3

    return float(np.rad2deg(so3.angle(rot)))
