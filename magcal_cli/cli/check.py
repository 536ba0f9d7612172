"""`magcal check`: judge the calibration a vehicle flew with (post-flight CI)."""

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
    verbosity,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from magcal_cli.calibration.types import Calibration
    from magcal_cli.firmware.check import CheckOptions, CheckReport
    from magcal_cli.firmware.gates import Condition


@click.command("check", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.option("calibration", help="The magcal calibration the vehicle flew with [default: the log's "
                                     "parameters].")
@options.option("params", help="The parameter file (or another log) the vehicle flew with [default: the log's "
                               "parameters].")
@click.option("--max-heading-error-deg", type=float, default=5.0, show_default=True,
              help="Fail when a compass's estimated heading error exceeds this (inf: no limit).")
@options.option("fail-on", callback=options.fail_on("check"),
                help="More failure conditions, e.g. 'interference_pct>30,field_norm_rms_pct>3' (see "
                     "docs/firmware-export.md).")
@options.mag("check")
@options.window("the log (the flight judged and the data of the new calibration)")
@click.option("--refit/--no-refit", default=True, show_default=True,
              help="Also calibrate the log anew and report the heading change that calibration would bring.")
@options.fmt
@click.option("--require-measured", is_flag=True,
              help="Fail (exit 3) when a gate cannot be measured from the log [default: reported as not measured].")
@options.as_json("Print the report as one JSON document.")
@verbosity
@click.pass_context
@handle_errors
def check_cmd(ctx: click.Context, log: Path, cal_path: Path | None, params_path: Path | None,
              max_heading_error_deg: float, fail_on: tuple[Any, ...], mags: tuple[str, ...], start_s: float | None,
              end_s: float | None, refit: bool, fmt: str | None, require_measured: bool, as_json: bool) -> None:
    """Judge the compass calibration LOG was flown with; exit 3 when a gate fails (post-flight CI).

    A gate the log cannot measure is reported as not measured and does not fail unless --require-measured.
    """
    from magcal_cli.firmware import gates
    from magcal_cli.firmware.check import CheckOptions
    from magcal_cli.firmware.flown import load_params

    if cal_path is not None and params_path is not None:
        msg = "give --calibration or --params, not both"
        raise click.UsageError(msg)
    guards.time_window(start_s, end_s)
    if max_heading_error_deg != max_heading_error_deg or max_heading_error_deg < 0:        # NaN or negative
        msg = "expected a number of degrees >= 0, or inf"
        raise click.BadParameter(msg, param_hint="--max-heading-error-deg")
    conditions = () if max_heading_error_deg == float("inf") else (
        gates.Condition("heading_error_deg", ">", max_heading_error_deg),)
    calibration = None if cal_path is None else guards.calibration_document(
        cal_path, "--calibration", "A log or parameter file the vehicle flew with goes to --params")
    source = (None if cal_path is None and params_path is None else
              f"the calibration document {cal_path.resolve()}" if cal_path is not None else
              f"the parameter file {params_path.resolve()}" if params_path is not None else None)
    with progress_line(ctx) as progress:            # current() for the refit, which run_check starts without a hook
        report = run_check(log, (*conditions, *fail_on), params=None if params_path is None else
                           load_params(params_path), calibration=calibration, mags=list(mags) or None, refit=refit,
                           fmt=fmt, progress=progress, options=CheckOptions(require_measured, source),
                           window=(start_s, end_s))
    click.echo(report.to_json() if as_json else report.to_text(), nl=False)
    if not report.passed:
        failed = [f"{c.id}: {', '.join(c.failed)}" for c in report.compasses if c.failed and c.gated]
        msg = f"check: {'; '.join(failed)}"
        raise QualityGateError(msg)


def run_check(log: Path, conditions: tuple[Condition, ...], *, params: dict[str, float] | None = None,
              calibration: Calibration | None = None, mags: list[str] | None = None, refit: bool = True,
              fmt: str | None = None, progress: Callable[[str], None] = lambda _: None,
              options: CheckOptions | None = None,
              window: tuple[float | None, float | None] = (None, None)) -> CheckReport:
    """Read `log`, refuse it when no flown calibration is known, optionally calibrate it anew, and check it;
    `window` (--start, --end) cuts both the flight judged and the new calibration's data."""
    from magcal_cli.cli.guards import windowed
    from magcal_cli.errors import MagcalError
    from magcal_cli.firmware.check import check_recording, flown_or_refuse
    from magcal_cli.pipeline import calibrate, command_config
    from magcal_cli.readers import open_recording
    from magcal_cli.streams import Kind

    progress(f"reading {log.name}")
    rec = windowed(open_recording(log, fmt), *window)
    flown = flown_or_refuse(rec, mags, params, calibration)         # before the refit, which takes long
    new, why = None, "skipped with --no-refit"
    if refit:
        progress("fitting a new calibration for comparison")
        try:
            ids = mags or [s.id for s in rec.of_kind(Kind.MAGNETOMETER)]
            new = calibrate(log, command_config(",".join(ids), start_s=window[0], end_s=window[1]),
                            fmt).calibration                    # what fit would give
        except MagcalError as exc:
            why = f"the new calibration failed: {str(exc).split(': ', 1)[-1]}"
    return check_recording(rec, conditions, params=params, calibration=calibration, mags=mags, new=new,
                           why_no_new=why, options=options, flown=flown)
