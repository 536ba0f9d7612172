"""`magcal fit`: calibrate every selected magnetometer of a log and write the results."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from magcal_cli.cli import options
from magcal_cli.cli.common import (
    AUTO,
    CONTEXT,
    EXIT_CODES,
    QualityGateError,
    effects_option,
    gates_option,
    handle_errors,
    parse_outputs,
    progress_line,
    say,
    verbosity,
    warning_lines,
)
from magcal_cli.config import Config
from magcal_cli.methods.table import CHOICES

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling


@click.command(context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--outdir", type=click.Path(path_type=Path), default=None,
              help="Output directory [default: ./<log stem>-magcal/].")
@options.mag("calibrate")
@click.option("--imu", "imu", default=None, help="IMU stream id [default: the first with accelerometer and gyro].")
@click.option("--method", type=click.Choice(CHOICES), default="auto", show_default=True,
              help="Calibration method; auto picks the best one available for the log. attitude: against the "
                   "vehicle's own attitude estimate and the World Magnetic Model (flight logs with GPS).")
@click.option("--outputs", default="json,yaml,report,plots", show_default=True,
              help="Comma-separated outputs to write: json, yaml, report, plots, ardupilot, px4 [the default "
                   "adds ardupilot.param for ArduPilot logs and px4.params for PX4 ULogs].")
@click.option("--start", "start_s", type=float, default=None, help="Use data from this time on (s from log start).")
@click.option("--end", "end_s", type=float, default=None, help="Use data up to this time (s from log start).")
@options.fmt
@click.option("--strict", is_flag=True,
              help="Refuse a cut log (one that ends inside a record) instead of reading it up to its last "
                   "complete record with a warning.")
@click.option("--allow-truncated", is_flag=True, hidden=True, expose_value=False,
              callback=lambda c, p, v: _deprecated(c, v),
              help="Deprecated: a cut log is read up to its last complete record by default.")
@options.as_json("Print the calibration document on stdout.")
@options.force()
@click.option("--location", default=None, metavar="LAT,LON[,ALT]", callback=options.location,
              help="Where the log was recorded (deg, deg, m): dip and field strength from the World Magnetic Model "
                   "[default: the log's position stream, if any].")
@click.option("--date", default=None, metavar="YYYY-MM-DD", callback=options.wmm_date,
              help="Date for the World Magnetic Model [default: the log's date when known, else today].")
@click.option("--robust-loss", type=click.Choice(["l2", "huber", "cauchy"]), default="l2", show_default=True,
              help="Joint MAP (--method map): down-weight outlying readings with a Huber or Cauchy loss.")
@click.option("--effects", "effects", default="auto", show_default=True, metavar="auto|none|ID[,ID...]",
              callback=effects_option,
              help="Physics beyond the base model (joint MAP; ekf-ml and ekf-aug carry current_interference and "
                   "temperature_drift, ekf-ml also throttle_interference). auto: the mismatch diagnosis tests every "
                   "effect the "
                   "log can test and adds what it proves on held-out data; none: the base model only; or a comma "
                   "list of effect ids to model exactly (current_interference, throttle_interference, "
                   "temperature_drift, time_offset, gyro_scale, accel_scale, lever_arm, nongravity_acceleration, "
                   "transient_disturbance), each reported with its estimate, uncertainty, test and status.")
@click.option("--fail-on", "fail_on", default=None, metavar="EXPR", callback=lambda c, p, v: gates_option(v, "fit"),
              help="Exit 3 when a magnetometer meets a condition, e.g. 'heading_std_deg>1,field_norm_rms_pct>2' "
                   "(METRIC OP NUMBER, comma-separated; see docs/firmware-export.md).")
@options.timing
@verbosity
@click.pass_context
@handle_errors
def fit(ctx: click.Context, log: Path, outdir: Path | None, mags: tuple[str, ...], imu: str | None, method: str,
        outputs: str, start_s: float | None, end_s: float | None, fmt: str | None, strict: bool, as_json: bool,
        force: bool, location: tuple[float, float, float] | None, date: str | None, robust_loss: str,
        effects: tuple[str, ...], fail_on: tuple[Any, ...], imu_timing: Sampling | None,
        mag_timing: Sampling | None) -> None:
    """Calibrate every selected magnetometer of LOG against the IMU and write the results."""
    from magcal_cli.calibration.document import dumps_json
    from magcal_cli.pipeline import calibrate
    from magcal_cli.writers import FIRMWARE_OUTPUTS

    options.time_window(start_s, end_s)
    names = parse_outputs(outputs)
    auto = _firmware_output(ctx, log, fmt, names)
    outdir = outdir or Path.cwd() / f"{log.stem}-magcal"
    _check_outdir(outdir, names + ([auto] if auto else []), force)
    cfg = Config(method=method, mag=",".join(mags) or "all", imu=imu, start_s=start_s, end_s=end_s,
                 allow_truncated=not strict, location=location, date=date, robust_loss=robust_loss,
                 effects=() if effects == AUTO else effects, diagnose=effects == AUTO, imu_timing=imu_timing,
                 mag_timing=mag_timing)
    with progress_line(ctx) as progress:
        result = calibrate(log, cfg, fmt, progress)
    if auto and FIRMWARE_OUTPUTS.get(result.recording.format) == auto:
        names.append(auto)
    written = _write_fit_outputs(ctx, result, outdir, names, auto)
    if result.recording.cut is not None:
        say(ctx, f"warning: {result.recording.cut.message}")
    if as_json:
        click.echo(dumps_json(result.calibration), nl=False)
        _fit_gates(result, fail_on)
        return
    for m in result.calibration.magnetometers:
        q = m.quality
        click.echo(f"{m.id}: {result.calibration.method}, dip {m.dip_deg:.1f} deg, misalignment "
                   f"{_angle_deg(m.misalignment):.2f} deg, field-norm error {q.field_norm_rms_pct:.2f} % RMS, "
                   f"coverage {q.coverage_pct:.0f} %" if q else m.id)
    lines = warning_lines(result.findings, [m.id for m in result.calibration.magnetometers],
                           bool(ctx.obj.get("verbose")))
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


def _check_outdir(outdir: Path, names: list[str], force: bool) -> None:
    """Before the work: no output of `names` exists in `outdir` without --force (exit 2), and it is writable."""
    from magcal_cli.atomic import check_writable
    from magcal_cli.writers import check_targets, get_writer

    options.refuse_existing((outdir / f for n in names for f in get_writer(n).files), force, ", or choose another -o")
    check_targets(outdir, names, force)
    check_writable(outdir, create=True, hint="Choose another -o")


def _write_fit_outputs(ctx: click.Context, result: Any, outdir: Path, names: list[str], auto: str | None
                       ) -> list[Path]:
    """fitrun.write_fit_outputs with its warnings on stderr (batch shares it)."""
    from magcal_cli.writers.fitrun import write_fit_outputs

    return write_fit_outputs(result, outdir, names, auto, lambda m: say(ctx, m))


def _deprecated(ctx: click.Context, value: bool) -> bool:
    """--allow-truncated: accepted for old scripts; a cut log is read by default now (--strict refuses it)."""
    if value:
        say(ctx, "--allow-truncated is deprecated: a cut log is read up to its last complete record by default")
    return value


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
