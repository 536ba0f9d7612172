"""The `magcal` command line: parse, call the pipeline, hand results to writers, map errors to exit codes."""

from __future__ import annotations

import functools
import json
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from . import __version__
from .config import Config
from .errors import MagcalError

F = TypeVar("F", bound=Callable[..., Any])
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
EXIT_CODES = ("Exit codes: 0 success; 1 the input could not be used (unreadable, truncated or unsupported log, "
              "missing stream, too little motion, no convergence); 2 usage error; 3 a quality gate failed; "
              "123 internal error (a bug).")
METHOD_CHOICES = ("auto", "kok2012", "map", "ekf-ml", "ekf-aug")


class QualityGateFailed(Exception):
    """A --fail-on or check threshold failed (exit 3)."""


def _stderr(ctx: click.Context, message: str) -> None:
    """Progress and remarks: stderr, silenced by -q."""
    if not ctx.obj.get("quiet"):
        click.echo(f"magcal: {message}", err=True)


def handle_errors(func: F) -> F:
    """Map MagcalError to exit 1, quality gates to 3, interrupts to 130 and anything else (a bug) to 123."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        try:
            return func(*args, **kwargs)
        except MagcalError as exc:
            raise click.ClickException(str(exc)) from None
        except QualityGateFailed as exc:
            click.echo(f"Error: {exc}", err=True)
            ctx.exit(3)
        except KeyboardInterrupt:
            click.echo("Error: interrupted; outputs not yet renamed into place were discarded.", err=True)
            ctx.exit(130)
        except (click.ClickException, click.exceptions.Exit):
            raise
        except Exception as exc:  # noqa: BLE001 - the last line of defence: a bug must not print a traceback
            if ctx.obj.get("verbose"):
                traceback.print_exc(file=sys.stderr)
            click.echo(f"Error: internal error ({type(exc).__name__}: {exc}). This is a bug in magcal; please "
                       "report it with the command and log" + ("" if ctx.obj.get("verbose") else
                                                                 "; run with -v for the traceback") + ".", err=True)
            ctx.exit(123)

    return wrapper  # type: ignore[return-value]


def verbosity(func: F) -> F:
    """-q/--quiet and -v/--verbose on a command."""

    def set_quiet(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["quiet"] = ctx.obj.get("quiet", False) or value

    def set_verbose(ctx: click.Context, _: click.Parameter, value: bool) -> None:
        ctx.ensure_object(dict)
        ctx.obj["verbose"] = ctx.obj.get("verbose", False) or value

    func = click.option("-q", "--quiet", is_flag=True, expose_value=False, callback=set_quiet,
                        help="Print nothing on stderr but errors.")(func)
    return click.option("-v", "--verbose", is_flag=True, expose_value=False, callback=set_verbose,
                        help="More detail on stderr; a traceback for internal errors.")(func)


@click.group(context_settings=CONTEXT, epilog=EXIT_CODES)
@click.version_option(__version__, "--version", prog_name="magcal", message="%(prog)s %(version)s")
@click.pass_context
def cli(ctx: click.Context) -> None:
    """Calibrate magnetometers jointly with an IMU from recorded logs (MCAP, ROS bags, ArduPilot, PX4)."""
    ctx.ensure_object(dict)


def _parse_outputs(value: str) -> list[str]:
    """The --outputs list, validated against the writer registry."""
    from .writers import WRITERS

    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [n for n in names if n not in WRITERS]
    if bad or not names:
        msg = f"unknown output(s) {', '.join(bad) or '(none)'}; choose from {', '.join(WRITERS)}"
        raise click.BadParameter(msg, param_hint="--outputs")
    return names


def _location(_: click.Context, __: click.Parameter, value: str | None) -> tuple[float, float, float] | None:
    """--location LAT,LON[,ALT] parsed, or a usage error."""
    from .errors import MagcalError
    from .wmm import parse_location

    try:
        return None if value is None else parse_location(value)
    except MagcalError as exc:
        raise click.BadParameter(str(exc)) from None


def _date(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--date YYYY-MM-DD checked, or a usage error."""
    from .errors import MagcalError
    from .wmm import parse_date

    try:
        return None if value is None else parse_date(value).isoformat()
    except MagcalError as exc:
        raise click.BadParameter(str(exc)) from None


@cli.command(epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--outdir", type=click.Path(path_type=Path), default=None,
              help="Output directory [default: ./<log stem>-magcal/].")
@click.option("--mag", "mag", default="all", show_default=True,
              help="Magnetometer stream id(s) to calibrate, comma-separated, or 'all'.")
@click.option("--imu", "imu", default=None, help="IMU stream id [default: the first with accelerometer and gyro].")
@click.option("--method", type=click.Choice(METHOD_CHOICES), default="auto", show_default=True,
              help="Calibration method; auto picks the best one available for the log.")
@click.option("--outputs", default="json,yaml,report,plots", show_default=True,
              help="Comma-separated outputs to write: json, yaml, report, plots.")
@click.option("--start", "start_s", type=float, default=None, help="Use data from this time on (s from log start).")
@click.option("--end", "end_s", type=float, default=None, help="Use data up to this time (s from log start).")
@click.option("--format", "fmt", default=None, help="Force the log format instead of sniffing it (e.g. mcap).")
@click.option("--allow-truncated", is_flag=True, help="Calibrate from the complete part of a truncated log.")
@click.option("--json", "as_json", is_flag=True, help="Print the calibration document on stdout.")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@click.option("--location", default=None, metavar="LAT,LON[,ALT]", callback=_location,
              help="Where the log was recorded (deg, deg, m): dip and field strength from the World Magnetic Model "
                   "[default: the log's position stream, if any].")
@click.option("--date", default=None, metavar="YYYY-MM-DD", callback=_date,
              help="Date for the World Magnetic Model [default: the log's date when known, else today].")
@click.option("--robust-loss", type=click.Choice(["l2", "huber", "cauchy"]), default="l2", show_default=True,
              help="Joint MAP (--method map): down-weight outlying readings with a Huber or Cauchy loss.")
@verbosity
@click.pass_context
@handle_errors
def fit(ctx: click.Context, log: Path, outdir: Path | None, mag: str, imu: str | None, method: str, outputs: str,
        start_s: float | None, end_s: float | None, fmt: str | None, allow_truncated: bool, as_json: bool,
        force: bool, location: tuple[float, float, float] | None, date: str | None, robust_loss: str) -> None:
    """Calibrate every selected magnetometer of LOG against the IMU and write the results."""
    from .document import dumps_json
    from .pipeline import calibrate
    from .writers import check_targets, get_writer

    names = _parse_outputs(outputs)
    outdir = outdir or Path.cwd() / f"{log.stem}-magcal"
    check_targets(outdir, names, force)
    cfg = Config(method=method, mag=mag, imu=imu, start_s=start_s, end_s=end_s, allow_truncated=allow_truncated,
                 location=location, date=date, robust_loss=robust_loss)
    result = calibrate(log, cfg, fmt, lambda m: _stderr(ctx, m))
    outdir.mkdir(parents=True, exist_ok=True)
    written = [p for name in names for p in get_writer(name).write(result, outdir)]
    if as_json:
        click.echo(dumps_json(result.calibration), nl=False)
        return
    for m in result.calibration.magnetometers:
        q = m.quality
        click.echo(f"{m.id}: {result.calibration.method}, dip {m.dip_deg:.1f} deg, misalignment "
                   f"{_angle_deg(m.misalignment):.2f} deg, field-norm error {q.field_norm_rms_pct:.2f} % RMS, "
                   f"coverage {q.coverage_pct:.0f} %" if q else m.id)
    for f in result.findings:
        if f.severity.value == "warning":
            _stderr(ctx, f"warning: {f.message}")
    for p in written:
        click.echo(f"wrote {p}")


def _angle_deg(rot: Any) -> float:
    """Rotation angle in degrees."""
    import numpy as np

    from . import so3

    return float(np.rad2deg(so3.angle(rot)))


@cli.command(epilog=EXIT_CODES)
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--scenario", type=click.Choice(["paper", "handheld"]), default="handheld", show_default=True,
              help="paper: the Huang et al. 2025 rotation protocol; handheld: still poses between hand rotations.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the truth, trajectory and noise.")
@click.option("--duration", type=float, default=None, help="Length in seconds [default: the scenario's own].")
@click.option("--rate", type=float, default=None, help="IMU rate in Hz [default: paper 80, handheld 100].")
@click.option("--mag-rate", type=float, default=None, help="Magnetometer rate in Hz [default: paper 80, handheld 50].")
@click.option("--truth", "truth_path", type=click.Path(path_type=Path), default=None,
              help="Where to write the truth [default: OUT.truth.json].")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@verbosity
@click.pass_context
@handle_errors
def simulate(ctx: click.Context, out: Path, scenario: str, seed: int, duration: float | None, rate: float | None,
             mag_rate: float | None, truth_path: Path | None, force: bool) -> None:
    """Write a synthetic log (format from OUT's extension) and its truth as a calibration document."""
    from .atomic import write_text
    from .document import dumps_json
    from .errors import OutputError
    from .logwriters import write_log
    from .pipeline import utc_now
    from .readers import open_recording
    from .synth import simulate as run_simulation
    from .synth import truth_calibration

    truth_path = truth_path or out.with_name(out.name + ".truth.json")
    for p in (out, truth_path):
        if p.exists() and not force:
            msg = f"{p}: exists already. Pass --force to overwrite it"
            raise OutputError(msg)
    _stderr(ctx, f"simulating {scenario} (seed {seed})")
    sim = run_simulation(scenario, seed, rate, mag_rate, duration)
    write_log(sim, out)
    written = open_recording(out)                       # the truth uses the ids and unit readers report
    write_text(truth_path, dumps_json(truth_calibration(sim, written, __version__, utc_now())))
    click.echo(f"wrote {out}")
    click.echo(f"wrote {truth_path}")


@cli.command("inspect", epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of the table.")
@click.option("--format", "fmt", default=None, help="Force the log format instead of sniffing it (e.g. mcap).")
@click.option("--receive-time", is_flag=True, help="ROS bags and MCAP: time samples by receive time, not header stamps.")
@verbosity
@click.pass_context
@handle_errors
def inspect_cmd(ctx: click.Context, log: Path, as_json: bool, fmt: str | None, receive_time: bool) -> None:
    """List the streams in LOG: id, kind, source, count, rate, start and end time, units."""
    from .inspect import inspect_log, to_json, to_table

    rec = inspect_log(log, fmt, receive_time)
    click.echo(to_json(rec) if as_json else to_table(rec))


def main() -> None:
    """Console entry point."""
    cli(prog_name="magcal")
