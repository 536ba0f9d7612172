"""The `magcal` command line: parse, call the pipeline, hand results to writers, map errors to exit codes."""

from __future__ import annotations

import functools
import re
import sys
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from magcal_cli import __version__
from magcal_cli.cli import options
from magcal_cli.config import Config
from magcal_cli.errors import MagcalError
from magcal_cli.writers import fitrun

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling

F = TypeVar("F", bound=Callable[..., Any])
MAG_HELP = ("Magnetometer stream id(s) to {what}; repeatable and comma-separated (e.g. --mag 'MAG[0],MAG[1]'), "
            "or 'all' [default: all].")
FORMAT_HELP = "Force the log format instead of sniffing it (e.g. mcap)."
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}
EXIT_CODES = ("Exit codes: 0 success; 1 the input could not be used (unreadable, truncated or unsupported log, "
              "missing stream, too little motion, no convergence); 2 usage error; 3 a quality gate failed; "
              "123 internal error (a bug); 130 interrupted (Ctrl-C), nothing half-written left. A closed pipe "
              "(e.g. | head) ends the command quietly with 1.")
METHOD_CHOICES = ("auto", "kok2012", "map", "ekf-ml", "ekf-aug", "attitude")


class QualityGateError(Exception):
    """A --fail-on or check threshold failed (exit 3)."""


def _stderr(ctx: click.Context, message: str) -> None:
    """Progress and remarks: stderr, silenced by -q."""
    if not ctx.obj.get("quiet"):
        click.echo(f"magcal: {message}", err=True)


def _progress(ctx: click.Context) -> Any:
    """The progress renderer on stderr (a context manager and the pipeline's hook): silent with -q, the live
    stage/fraction/time-left line only when stderr is a terminal."""
    from magcal_cli.progress import Progress

    return Progress.for_stderr(bool(ctx.obj.get("quiet")))


#: finding code -> its one-line form in the terminal ({max_factor} and {what} filled from the group's evidence)
BRIEF = {"correlated_residuals": "residuals correlated in time beyond the noise model (uncertainty widened up to "
                                 "{max_factor:.1f}x)",
         "poorly_observable": "{what} poorly determined by the motion in this log (docs/recording-guide.md says "
                              "which motion determines it)",
         "dip_disagrees_with_wmm": "fitted dip differs from the World Magnetic Model's"}
#: a kind with a single warning no longer than this is printed in full
FULL_CHARS = 240


def _warning_lines(findings: tuple[Any, ...], mag_ids: list[str], verbose: bool) -> list[str]:
    """The fit's warnings for the terminal: every one in full with -v, else one line per kind naming the
    magnetometers (report.html and report.txt keep the full text)."""
    from magcal_cli.findings import Severity
    from magcal_cli.writers.report.summary import groups

    warnings = tuple(f for f in findings if f.severity is Severity.WARNING)
    if verbose:
        return [f.message for f in warnings]
    out = []
    for g in groups(warnings, mag_ids):
        if len(g.messages) == 1 and len(g.messages[0]) <= FULL_CHARS:
            out.append(g.messages[0])
            continue
        mine = [f for f in warnings if f.code == g.code]
        factor = max((float(f.evidence.get("max_factor", 0.0)) for f in mine), default=0.0)
        what = sorted({m.group(1) for f in mine if (m := re.search(r"leaves the (.+?) poorly determined", f.message))})
        text = BRIEF.get(g.code, g.title[:1].lower() + g.title[1:]).format(max_factor=factor,
                                                                           what=", ".join(what) or "parameters")
        who = ", ".join(g.sensors) if len(g.sensors) < 3 else f"{len(g.sensors)} magnetometers ({', '.join(g.sensors)})"
        out.append(f"{who}: {text}" if who else text)
    return out


def handle_errors(func: F) -> F:
    """Map MagcalError to exit 1, quality gates to 3, interrupts to 130 and anything else (a bug) to 123."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        ctx = click.get_current_context()
        try:
            return func(*args, **kwargs)
        except MagcalError as exc:
            raise click.ClickException(str(exc)) from None
        except QualityGateError as exc:
            click.echo(f"Error: {exc}", err=True)
            ctx.exit(3)
        except KeyboardInterrupt:
            click.echo("Error: interrupted; outputs not yet renamed into place were discarded.", err=True)
            ctx.exit(130)
        except (click.ClickException, click.exceptions.Exit, BrokenPipeError):
            raise                       # click's main: a closed stdout (| head) exits 1 quietly
        except OSError as exc:
            if exc.errno not in USER_ERRNOS:
                _internal_error(ctx, exc)
            where = exc.filename or "magcal"
            msg = f"{where}: {exc.strerror or exc}. Check the path, its permissions and free space"
            raise click.ClickException(msg) from None
        except Exception as exc:  # noqa: BLE001 - the last line of defence: a bug must not print a traceback
            _internal_error(ctx, exc)

    return wrapper  # type: ignore[return-value]


def _internal_error(ctx: click.Context, exc: BaseException) -> None:
    """A bug: one line (the traceback with -v), exit 123."""
    if ctx.obj.get("verbose"):
        traceback.print_exception(exc, file=sys.stderr)
    click.echo(f"Error: internal error ({type(exc).__name__}: {exc}). This is a bug in magcal; please "
               "report it with the command and log" + ("" if ctx.obj.get("verbose") else
                                                         "; run with -v for the traceback") + ".", err=True)
    ctx.exit(123)


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
    from magcal_cli.writers import WRITERS

    names = [v.strip() for v in value.split(",") if v.strip()]
    bad = [n for n in names if n not in WRITERS]
    if bad or not names:
        msg = f"unknown output(s) {', '.join(bad) or '(none)'}; choose from {', '.join(WRITERS)}"
        raise click.BadParameter(msg, param_hint="--outputs")
    return names


def _date(_: click.Context, __: click.Parameter, value: str | None) -> str | None:
    """--date YYYY-MM-DD checked, or a usage error."""
    from magcal_cli.errors import MagcalError
    from magcal_cli.wmm import parse_date

    try:
        return None if value is None else parse_date(value).isoformat()
    except MagcalError as exc:
        raise click.BadParameter(str(exc)) from None


#: the file system refusing a read or write: the user's environment, not a bug (exit 1, not 123); batch shares it
USER_ERRNOS = fitrun.USER_ERRNOS

#: what --effects auto parses to: the diagnosis chooses the effects
AUTO = ("auto",)


def _effects(_: click.Context, __: click.Parameter, value: str) -> tuple[str, ...]:
    """--effects parsed into effect ids, or AUTO."""
    from magcal_cli.effects import EffectError, parse

    if value.strip() == "auto":
        return AUTO
    try:
        return parse(value)
    except EffectError as exc:
        raise click.BadParameter(str(exc).removeprefix("--effects: ")) from None


@cli.command(epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--outdir", type=click.Path(path_type=Path), default=None,
              help="Output directory [default: ./<log stem>-magcal/].")
@click.option("--mag", "mags", multiple=True, callback=options.mag_ids, metavar="ID[,ID...]|all",
              help=MAG_HELP.format(what="calibrate"))
@click.option("--imu", "imu", default=None, help="IMU stream id [default: the first with accelerometer and gyro].")
@click.option("--method", type=click.Choice(METHOD_CHOICES), default="auto", show_default=True,
              help="Calibration method; auto picks the best one available for the log. attitude: against the "
                   "vehicle's own attitude estimate and the World Magnetic Model (flight logs with GPS).")
@click.option("--outputs", default="json,yaml,report,plots", show_default=True,
              help="Comma-separated outputs to write: json, yaml, report, plots, ardupilot, px4 [the default "
                   "adds ardupilot.param for ArduPilot logs and px4.params for PX4 ULogs].")
@click.option("--start", "start_s", type=float, default=None, help="Use data from this time on (s from log start).")
@click.option("--end", "end_s", type=float, default=None, help="Use data up to this time (s from log start).")
@click.option("--format", "fmt", default=None, callback=options.log_format, help=FORMAT_HELP)
@click.option("--strict", is_flag=True,
              help="Refuse a cut log (one that ends inside a record) instead of reading it up to its last "
                   "complete record with a warning.")
@click.option("--allow-truncated", is_flag=True, hidden=True, expose_value=False,
              callback=lambda c, p, v: _deprecated(c, v),
              help="Deprecated: a cut log is read up to its last complete record by default.")
@click.option("--json", "as_json", is_flag=True, help="Print the calibration document on stdout.")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@click.option("--location", default=None, metavar="LAT,LON[,ALT]", callback=options.location,
              help="Where the log was recorded (deg, deg, m): dip and field strength from the World Magnetic Model "
                   "[default: the log's position stream, if any].")
@click.option("--date", default=None, metavar="YYYY-MM-DD", callback=_date,
              help="Date for the World Magnetic Model [default: the log's date when known, else today].")
@click.option("--robust-loss", type=click.Choice(["l2", "huber", "cauchy"]), default="l2", show_default=True,
              help="Joint MAP (--method map): down-weight outlying readings with a Huber or Cauchy loss.")
@click.option("--effects", "effects", default="auto", show_default=True, metavar="auto|none|ID[,ID...]",
              callback=_effects,
              help="Physics beyond the base model (joint MAP; ekf-ml and ekf-aug carry current_interference and "
                   "temperature_drift, ekf-ml also throttle_interference). auto: the mismatch diagnosis tests every "
                   "effect the "
                   "log can test and adds what it proves on held-out data; none: the base model only; or a comma "
                   "list of effect ids to model exactly (current_interference, throttle_interference, "
                   "temperature_drift, time_offset, gyro_scale, accel_scale, lever_arm, nongravity_acceleration, "
                   "transient_disturbance), each reported with its estimate, uncertainty, test and status.")
@click.option("--fail-on", "fail_on", default=None, metavar="EXPR", callback=lambda c, p, v: _gates(v, "fit"),
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
    names = _parse_outputs(outputs)
    auto = _firmware_output(ctx, log, fmt, names)
    outdir = outdir or Path.cwd() / f"{log.stem}-magcal"
    _check_outdir(outdir, names + ([auto] if auto else []), force)
    cfg = Config(method=method, mag=",".join(mags) or "all", imu=imu, start_s=start_s, end_s=end_s,
                 allow_truncated=not strict, location=location, date=date, robust_loss=robust_loss,
                 effects=() if effects == AUTO else effects, diagnose=effects == AUTO, imu_timing=imu_timing,
                 mag_timing=mag_timing)
    with _progress(ctx) as progress:
        result = calibrate(log, cfg, fmt, progress)
    if auto and FIRMWARE_OUTPUTS.get(result.recording.format) == auto:
        names.append(auto)
    written = _write_fit_outputs(ctx, result, outdir, names, auto)
    if result.recording.cut is not None:
        _stderr(ctx, f"warning: {result.recording.cut.message}")
    if as_json:
        click.echo(dumps_json(result.calibration), nl=False)
        _fit_gates(result, fail_on)
        return
    for m in result.calibration.magnetometers:
        q = m.quality
        click.echo(f"{m.id}: {result.calibration.method}, dip {m.dip_deg:.1f} deg, misalignment "
                   f"{_angle_deg(m.misalignment):.2f} deg, field-norm error {q.field_norm_rms_pct:.2f} % RMS, "
                   f"coverage {q.coverage_pct:.0f} %" if q else m.id)
    lines = _warning_lines(result.findings, [m.id for m in result.calibration.magnetometers],
                           bool(ctx.obj.get("verbose")))
    for line in lines:
        _stderr(ctx, f"warning: {line}")
    full = sum(f.severity.value == "warning" for f in result.findings)
    report = next((p for name in ("report.html", "report.txt") for p in written if p.name == name), None)
    if full > len(lines):
        _stderr(ctx, f"{full} warnings in {len(lines)} kinds; the full text is in "
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

    return write_fit_outputs(result, outdir, names, auto, lambda m: _stderr(ctx, m))


def _deprecated(ctx: click.Context, value: bool) -> bool:
    """--allow-truncated: accepted for old scripts; a cut log is read by default now (--strict refuses it)."""
    if value:
        _stderr(ctx, "--allow-truncated is deprecated: a cut log is read up to its last complete record by default")
    return value


def _gates(value: str | None, command: str) -> tuple[Any, ...]:
    """--fail-on parsed against the metrics `command` measures, or a usage error."""
    from magcal_cli.firmware import gates

    if value is None:
        return ()
    if command == "fit":
        from magcal_cli.firmware.metrics import METRICS
    else:
        from magcal_cli.firmware.check import METRICS
    try:
        return gates.parse(value, METRICS)
    except MagcalError as exc:
        raise click.BadParameter(str(exc).split(": ", 1)[-1], param_hint="--fail-on") from None


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


def _parse_effects(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[Any, ...]:
    """--effect values as EffectSpecs (SI), each id once; a bad one is click's usage error (exit 2)."""
    from magcal_cli.synth.effects import EffectSpecError, check_unique, parse_effect

    try:
        specs = tuple(parse_effect(v) for v in values)
        check_unique(specs)
    except EffectSpecError as exc:
        raise click.BadParameter(str(exc), ctx, param) from None
    return specs


def _effect_help() -> str:
    """The --effect help: syntax, units and every id with its keys."""
    from magcal_cli.synth.effects import syntax

    return ("Inject a physical effect (repeatable): ID[:key=value,...]. Vectors are x/y/z "
            "(e.g. c_uT_per_A=0.2/-0.1/0.3), windows t0-t1/t0-t1 in s; omitted keys take their defaults. "
            f"Ids (keys): {syntax()}. See docs/simulate-effects.md.")


@cli.command(epilog=EXIT_CODES)
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--scenario", type=click.Choice(["paper", "handheld", "multirotor", "rover"]), default="handheld",
              show_default=True,
              help="paper: the Huang et al. 2025 rotation protocol; handheld: still poses between hand rotations; "
                   "multirotor: 300 s flight (tilt within about 20 deg, full yaw turns, accelerating, GPS logged; "
                   "100/50 Hz); rover: 300 s drive (circles, figure-eights, tilt within 5 deg, GPS; 100/50 Hz). "
                   "See docs/simulate-scenarios.md.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the truth, trajectory and noise.")
@click.option("--duration", type=float, default=None, help="Length in seconds [default: the scenario's own].")
@click.option("--rate", type=float, default=None, help="IMU rate in Hz [default: paper 80, handheld 100].")
@click.option("--mag-rate", type=float, default=None,
              help="Magnetometer rate in Hz, any positive rate (a .csv needs one that divides --rate) "
                   "[default: paper 80, handheld 50].")
@click.option("--mag-phase", type=float, default=None, metavar="SECONDS",
              help="Time of the first magnetometer stamp after the first IMU stamp, >= 0 and below one "
                   "magnetometer period [default: drawn from --seed in 0-5 ms, as real boards stamp it; 0 for a "
                   ".csv, which holds one row per IMU sample].")
@click.option("--effect", "effects", multiple=True, metavar="ID[:key=value,...]", callback=_parse_effects,
              help=_effect_help())
@click.option("--truth", "truth_path", type=click.Path(path_type=Path), default=None,
              help="Where to write the truth [default: OUT.truth.json].")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@verbosity
@click.pass_context
@handle_errors
def simulate(ctx: click.Context, out: Path, scenario: str, seed: int, duration: float | None, rate: float | None,
             mag_rate: float | None, mag_phase: float | None, effects: tuple[Any, ...], truth_path: Path | None,
             force: bool) -> None:
    """Write a synthetic log (format from OUT's extension) and its truth as a calibration document.

    The IMU samples the way OUT's format defines (instantaneous, or the mean over the last IMU period in a .ulg);
    the magnetometer has its own rate and phase. The truth lists the injected effects in the log's magnetometer
    unit and with the reader's channel ids.
    """
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.calibration.document import dumps_json
    from magcal_cli.pipeline import utc_now
    from magcal_cli.readers import open_recording
    from magcal_cli.synth.logs import imu_sampling, write_log
    from magcal_cli.synth.simulate import simulate as run_simulation
    from magcal_cli.synth.simulate import truth_calibration

    truth_path = truth_path or out.with_name(out.name + ".truth.json")
    options.log_extension(out)
    mag_phase = _mag_phase(out, scenario, rate, mag_rate, mag_phase)
    options.refuse_existing((out, truth_path), force)
    for p in (out, truth_path):
        check_writable(p.parent, hint="Choose another path")
    _stderr(ctx, f"simulating {scenario} (seed {seed})" + (f" with {', '.join(e.id for e in effects)}"
                                                             if effects else ""))
    sim = run_simulation(scenario, seed, rate, mag_rate, duration, effects=effects, imu_sampling=imu_sampling(out),
                         mag_phase_s=mag_phase)
    write_log(sim, out)
    written = open_recording(out)                       # the truth uses the ids and unit readers report
    write_text(truth_path, dumps_json(truth_calibration(sim, written, __version__, utc_now())))
    click.echo(f"wrote {out}")
    click.echo(f"wrote {truth_path}")


def _mag_phase(out: Path, scenario: str, rate: float | None, mag_rate: float | None,
               phase: float | None) -> float | None:
    """--mag-phase checked (a usage error outside [0, 1/mag-rate)); a .csv, whose rows are the IMU samples, takes
    phase 0 and needs a magnetometer rate that divides the IMU rate."""
    from magcal_cli.synth.simulate import rates

    rate_hz, mag_hz = rates(scenario, rate, mag_rate)
    if phase is not None and not (0.0 <= phase < 1.0 / mag_hz if mag_hz > 0 else phase >= 0.0):
        msg = f"must be >= 0 s and below one magnetometer period (1/{mag_hz:g} Hz = {1.0 / mag_hz:g} s), got {phase:g}"
        raise click.BadParameter(msg, param_hint="--mag-phase")
    if out.suffix.lower() != ".csv":
        return phase
    if phase:
        msg = f"{out}: a .csv log holds one row per IMU sample, so its magnetometer has phase 0; drop --mag-phase"
        raise click.BadParameter(msg, param_hint="--mag-phase")
    ratio = rate_hz / mag_hz if mag_hz > 0 else 0.0
    if ratio < 1.0 or abs(ratio - round(ratio)) > 1e-9:
        msg = (f"{out}: a .csv log holds one row per IMU sample, so the magnetometer rate must divide the IMU rate "
               f"{rate_hz:g} Hz; got {mag_hz:g} Hz")
        raise click.BadParameter(msg, param_hint="--mag-rate")
    return 0.0


@cli.command("inspect", epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of the table.")
@click.option("--format", "fmt", default=None, callback=options.log_format, help=FORMAT_HELP)
@click.option("--receive-time", is_flag=True, help="ROS bags and MCAP: time samples by receive time, not header stamps.")
@verbosity
@click.pass_context
@handle_errors
def inspect_cmd(ctx: click.Context, log: Path, as_json: bool, fmt: str | None, receive_time: bool) -> None:
    """List the streams in LOG: id, kind, source, count, rate, start and end time, units."""
    from magcal_cli.readers.inspect import inspect_log, to_json, to_table

    rec = inspect_log(log, fmt, receive_time)
    click.echo(to_json(rec) if as_json else to_table(rec))


#: log formats that carry the vehicle's parameters, which `export` reads from a document's source log
PARAM_FORMATS = ("dataflash", "ulog")


def _vehicle_params(ctx: click.Context, params_path: Path | None, cal_path: Path, cal: Any) -> dict[str, float]:
    """--params (a parameter file or a log), else the document's source log; refused when that log is missing
    but would have held the parameters (the export would silently differ)."""
    from magcal_cli.firmware.flown import load_params

    if params_path is not None:
        return load_params(params_path)
    source = cal.source.path
    src = Path(source)
    if source and src.is_file():
        _stderr(ctx, f"vehicle parameters from the document's source log {src.name}")
        try:
            return load_params(src)
        except MagcalError as exc:
            _stderr(ctx, f"warning: {exc}")
    elif source and cal.source.format in PARAM_FORMATS:
        msg = (f"{cal_path}: the source log {src} is missing, so the vehicle's parameters (compass slots, "
               "orientations, device ids) are unknown and the parameters would differ. Restore the log, or pass "
               "--params with the log or the vehicle's parameter file")
        raise MagcalError(msg)
    return {}


@cli.command("export", epilog=EXIT_CODES)
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--ardupilot", "ardupilot_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write ArduPilot COMPASS_* parameters to this file (Mission Planner NAME,VALUE).")
@click.option("--px4", "px4_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write PX4 CAL_MAGn_* parameters to this file (QGroundControl .params).")
@click.option("--style", type=click.Choice(["default", "mavproxy", "nsh"]), default="default", show_default=True,
              help="default: Mission Planner .param / QGroundControl .params; mavproxy: 'NAME VALUE' lines "
                   "(ArduPilot); nsh: 'param set NAME VALUE' lines (PX4).")
@click.option("--mag", "mags", multiple=True, callback=options.mag_ids, metavar="ID[,ID...]|all",
              help=MAG_HELP.format(what="export"))
@click.option("--slot", type=int, default=None,
              help="Parameter slot for one --mag: ArduPilot 1-3, PX4 0-3 [default: from the device ids].")
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), default=None,
              help="The vehicle's parameters (.param/.params file or a log): slots, orientations, features "
                   "[default: the document's source log, if it exists].")
@click.option("--rotation", type=click.Choice(["auto", "enum", "custom"]), default="auto", show_default=True,
              help="External compasses: the nearest orientation enum, custom Euler angles, or auto (custom when "
                   "the enum misses by more than --custom-above-deg and the firmware has custom rotations).")
@click.option("--custom-above-deg", type=float, default=1.0, show_default=True,
              help="With --rotation auto: use a custom rotation when the nearest enum misses by more than this.")
@click.option("--external/--internal", default=None,
              help="Treat the compass as external/internal when the vehicle parameters do not say "
                   "[default: internal].")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@verbosity
@click.pass_context
@handle_errors
def export_cmd(ctx: click.Context, calibration: Path, ardupilot_out: Path | None, px4_out: Path | None, style: str,
               mags: tuple[str, ...], slot: int | None, params_path: Path | None, rotation: str,
               custom_above_deg: float, external: bool | None, force: bool) -> None:
    """Write firmware parameters for the calibration in CALIBRATION (a magcal document)."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.firmware.export import Options, export
    from magcal_cli.firmware.paramfile import render

    targets = [(fw, out) for fw, out in (("ardupilot", ardupilot_out), ("px4", px4_out)) if out is not None]
    if not targets:
        msg = "give --ardupilot OUT.param or --px4 OUT.params"
        raise click.UsageError(msg)
    kinds = {fw: {"default": "mission-planner" if fw == "ardupilot" else "qgc"}.get(style, style) for fw, _ in targets}
    for firmware, kind in kinds.items():
        if (firmware, kind) in (("ardupilot", "nsh"), ("px4", "mavproxy")):
            msg = f"{style} is not a {firmware} parameter format"
            raise click.BadParameter(msg, param_hint="--style")
    if slot is not None and len(mags) > 1:
        msg = f"--slot applies to one magnetometer, but --mag gives {len(mags)} ({', '.join(mags)}); give one --mag"
        raise click.UsageError(msg)
    cal = options.calibration_document(calibration, "CALIBRATION", "Run: magcal export CAL.json --ardupilot "
                                       "OUT.param (or --px4 OUT.params); a log with the vehicle's parameters goes "
                                       "to --params")
    options.refuse_existing((out for _, out in targets), force)
    for _, out in targets:
        check_writable(out.parent, hint="Choose another output file")
    params = _vehicle_params(ctx, params_path, calibration, cal)
    opts = Options(rotation, custom_above_deg, external, slot)
    for firmware, out in targets:
        exp = export(cal, firmware, params, opts, list(mags) or None)
        for line in exp.notes + exp.warnings:
            _stderr(ctx, line)
        for m in exp.mags:
            click.echo(m.lost_text())
        write_text(out, render(exp.params, kinds[firmware], exp.header(), exp.integers))
        click.echo(f"wrote {out}")


@cli.command("apply", epilog=EXIT_CODES)
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--output", "out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="CSV file to write: t [s], id, the calibrated field x, y, z and its magnitude ('-': standard "
                   "output).")
@click.option("--mag", "mags", multiple=True, callback=options.mag_ids, metavar="ID[,ID...]|all",
              help=MAG_HELP.format(what="apply"))
@click.option("--format", "fmt", default=None, callback=options.log_format, help=FORMAT_HELP)
@click.option("--force", is_flag=True, help="Overwrite an existing output.")
@verbosity
@click.pass_context
@handle_errors
def apply_cmd(ctx: click.Context, calibration: Path, log: Path, out: Path, mags: tuple[str, ...], fmt: str | None,
              force: bool) -> None:
    """Apply CALIBRATION to LOG and write the calibrated field over time as CSV."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.calibration.apply import apply_to_recording
    from magcal_cli.readers import open_recording

    cal = options.calibration_document(calibration, "CALIBRATION", "The arguments look swapped; run: magcal "
                                       "apply CAL.json LOG -o OUT.csv")
    stdout = str(out) == "-"                  # as Unix tools read it, not a file named '-'
    if not stdout:
        options.refuse_existing((out,), force, ", or choose another -o")
        check_writable(out.parent, hint="Choose another -o")
    rec = open_recording(log, fmt)
    if rec.cut is not None:
        _stderr(ctx, f"warning: {rec.cut.message}")
    text, notes = apply_to_recording(cal, rec, list(mags) or None)
    for n in notes:
        _stderr(ctx, n)
    if stdout:
        click.echo(text, nl=False)
        return
    write_text(out, text)
    click.echo(f"wrote {out}")


@cli.command("diagnose", epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=None, help="A magcal calibration of this vehicle: its magnetometers and IMU are diagnosed "
                                 "[default: every magnetometer of the log].")
@click.option("-o", "--outdir", type=click.Path(path_type=Path), default=None,
              help="Also write diagnosis.json (the diagnosis and every effect's verdict) to this directory.")
@click.option("--json", "as_json", is_flag=True, help="Print the diagnosis and the effects as one JSON document.")
@click.option("--force", is_flag=True, help="Overwrite an existing diagnosis.json.")
@click.option("--format", "fmt", default=None, callback=options.log_format, help=FORMAT_HELP)
@options.timing
@verbosity
@click.pass_context
@handle_errors
def diagnose_cmd(ctx: click.Context, log: Path, cal_path: Path | None, outdir: Path | None, as_json: bool,
                 force: bool, fmt: str | None, imu_timing: Sampling | None, mag_timing: Sampling | None) -> None:
    """Find what physics the calibrated model leaves out of LOG, model it, and show the held-out improvement."""
    import json

    from magcal_cli.atomic import atomic_path, check_writable
    from magcal_cli.pipeline import calibrate

    mag, imu = "all", None
    if cal_path is not None:
        cal = options.calibration_document(cal_path, "--calibration",
                                           "Give the calibration, or leave --calibration out")
        mag, imu = ",".join(m.id for m in cal.magnetometers), cal.imu.id
    target = None if outdir is None else outdir / "diagnosis.json"
    if outdir is not None and target is not None:
        options.refuse_existing((target,), force, ", or choose another -o")
        check_writable(outdir, create=True, hint="Choose another -o")
    cfg = Config(method="map", mag=mag, imu=imu, diagnose=True, imu_timing=imu_timing, mag_timing=mag_timing)
    with _progress(ctx) as progress:
        result = calibrate(log, cfg, fmt, progress)
    doc = {"log": str(log.resolve()), "diagnosis": result.calibration.diagnosis,
           "effects": list(result.calibration.effects)}
    text = json.dumps(doc, indent=2, default=float) + "\n"
    if target is not None:
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tmp.write_text(text)
    if as_json:
        click.echo(text, nl=False)
        return
    for block in (result.calibration.diagnosis or {}).get("sensors", []):
        click.echo(block["summary"])
    if target is not None:
        click.echo(f"wrote {target}")


@cli.command("check", epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=None, help="The magcal calibration the vehicle flew with [default: the log's parameters].")
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), default=None,
              help="The parameter file (or another log) the vehicle flew with [default: the log's parameters].")
@click.option("--max-heading-error-deg", type=float, default=5.0, show_default=True,
              help="Fail when a compass's estimated heading error exceeds this (inf: no limit).")
@click.option("--fail-on", "fail_on", default=None, metavar="EXPR", callback=lambda c, p, v: _gates(v, "check"),
              help="More failure conditions, e.g. 'interference_pct>30,field_norm_rms_pct>3' (see "
                   "docs/firmware-export.md).")
@click.option("--mag", "mags", multiple=True, callback=options.mag_ids, metavar="ID[,ID...]|all",
              help=MAG_HELP.format(what="check"))
@click.option("--refit/--no-refit", default=True, show_default=True,
              help="Also calibrate the log anew and report the heading change that calibration would bring.")
@click.option("--format", "fmt", default=None, callback=options.log_format, help=FORMAT_HELP)
@click.option("--require-measured", is_flag=True,
              help="Fail (exit 3) when a gate cannot be measured from the log [default: reported as not measured].")
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON document.")
@verbosity
@click.pass_context
@handle_errors
def check_cmd(ctx: click.Context, log: Path, cal_path: Path | None, params_path: Path | None,
              max_heading_error_deg: float, fail_on: tuple[Any, ...], mags: tuple[str, ...], refit: bool,
              fmt: str | None, require_measured: bool, as_json: bool) -> None:
    """Judge the compass calibration LOG was flown with; exit 3 when a gate fails (post-flight CI).

    A gate the log cannot measure is reported as not measured and does not fail unless --require-measured.
    """
    from magcal_cli.firmware import gates
    from magcal_cli.firmware.check import CheckOptions, run_check
    from magcal_cli.firmware.flown import load_params

    if cal_path is not None and params_path is not None:
        msg = "give --calibration or --params, not both"
        raise click.UsageError(msg)
    if max_heading_error_deg != max_heading_error_deg or max_heading_error_deg < 0:        # NaN or negative
        msg = "expected a number of degrees >= 0, or inf"
        raise click.BadParameter(msg, param_hint="--max-heading-error-deg")
    conditions = () if max_heading_error_deg == float("inf") else (
        gates.Condition("heading_error_deg", ">", max_heading_error_deg),)
    calibration = None if cal_path is None else options.calibration_document(
        cal_path, "--calibration", "A log or parameter file the vehicle flew with goes to --params")
    source = (None if cal_path is None and params_path is None else
              f"the calibration document {cal_path.resolve()}" if cal_path is not None else
              f"the parameter file {params_path.resolve()}" if params_path is not None else None)
    with _progress(ctx) as progress:            # current() for the refit, which run_check starts without a hook
        report = run_check(log, (*conditions, *fail_on), params=None if params_path is None else
                           load_params(params_path), calibration=calibration, mags=list(mags) or None, refit=refit,
                           fmt=fmt, progress=progress, options=CheckOptions(require_measured, source))
    click.echo(report.to_json() if as_json else report.to_text(), nl=False)
    if not report.passed:
        failed = [f"{c.id}: {', '.join(c.failed)}" for c in report.compasses if c.failed and c.gated]
        msg = f"check: {'; '.join(failed)}"
        raise QualityGateError(msg)


BATCH_EXIT = ("Exit codes: 0 every log fitted (or up to date); 1 a log could not be fitted (each log's own exit code, "
              "as magcal fit would give it, is in the table and the JSON); 2 usage error (no log found, an output "
              "that exists without --force); 3 a log failed a --fail-on gate (and none failed otherwise); 123 "
              "internal error; 130 interrupted (Ctrl-C), nothing half-written left.")


@cli.command("batch", epilog=BATCH_EXIT)
@click.argument("inputs", nargs=-1, required=True, metavar="INPUT...")
@click.option("-o", "--outdir", type=click.Path(path_type=Path), required=True,
              help="Output directory: each log's outputs go to DIR/<log stem>/ (a longer unique name when stems "
                   "collide), with the batch.json status that makes a rerun skip it.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None,
              help="Local worker processes, one log at a time each [default: the number of cores].")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Fit on the Dask cluster at this scheduler (e.g. tcp://10.0.0.5:8786) instead of local processes; "
                   "the workers need the same paths and magcal with: pip install 'magcal-cli[fleet]'.")
@click.option("--mag", "mags", multiple=True, callback=options.mag_ids, metavar="ID[,ID...]|all",
              help=MAG_HELP.format(what="calibrate in every log"))
@click.option("--method", type=click.Choice(METHOD_CHOICES), default="auto", show_default=True,
              help="Calibration method, as in magcal fit.")
@click.option("--effects", "effects", default="auto", show_default=True, metavar="auto|none|ID[,ID...]",
              callback=_effects, help="Physics beyond the base model, as in magcal fit.")
@click.option("--outputs", default=None,
              help="Comma-separated outputs per log, as in magcal fit [default: json,yaml,report,plots and the "
                   "firmware file of ArduPilot and PX4 logs].")
@click.option("--fail-on", "fail_on", default=None, metavar="EXPR", callback=lambda c, p, v: _gates(v, "fit"),
              help="A log whose magnetometer meets a condition is 'gate failed' (its exit 3), as in magcal fit.")
@click.option("--strict", is_flag=True, help="Refuse cut logs instead of reading them up to their last record.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document with one entry per log.")
@click.option("--force", is_flag=True, help="Overwrite outputs that are not up to date (up-to-date logs are "
                                              "still skipped; remove DIR/<log>/batch.json to refit one).")
@options.timing
@verbosity
@click.pass_context
@handle_errors
def batch_cmd(ctx: click.Context, inputs: tuple[str, ...], outdir: Path, jobs: int | None, scheduler: str | None,
              mags: tuple[str, ...], method: str, effects: tuple[str, ...], outputs: str | None,
              fail_on: tuple[Any, ...], strict: bool, as_json: bool, force: bool, imu_timing: Sampling | None,
              mag_timing: Sampling | None) -> None:
    """Fit many logs (files, folders searched recursively, globs) in parallel, locally or on a Dask cluster.

    Each log is fitted as 'magcal fit LOG -o DIR/<name>/' would; logs whose outputs are complete and newer than
    the log are skipped, and a failing log never stops the others. The summary goes to stdout.
    """
    import os
    import time

    from magcal_cli.batch.plan import BatchUsageError, FitOptions, discover, exit_code, plan
    from magcal_cli.batch.report import Runner, document, progress_line, table

    if jobs is not None and scheduler is not None:
        msg = "--jobs sets local processes; with --scheduler the cluster's workers fit the logs. Give one of them"
        raise click.UsageError(msg)
    if scheduler is not None:
        from magcal_cli.batch.dask import require_distributed

        require_distributed()                       # before any work: one line naming the extra to install
    names = None if outputs is None else tuple(_parse_outputs(outputs))
    opts = FitOptions(method, effects, names, mags, fail_on, strict, imu_timing, mag_timing)
    try:
        work = plan(discover(list(inputs), outdir), outdir, opts, force)
    except BatchUsageError as exc:
        raise click.UsageError(str(exc)) from None
    workers = jobs or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    where = f"the Dask cluster at {scheduler}" if scheduler else f"{workers} local worker{'s' * (workers != 1)}"
    _stderr(ctx, f"{len(work.order)} logs: {len(work.jobs)} to fit, {len(work.skipped)} up to date; fitting on {where}")
    count = [0]

    def done(r: Any) -> None:
        count[0] += 1
        _stderr(ctx, progress_line(r, count[0], len(work.order)))
        if r.traceback and ctx.obj.get("verbose"):
            click.echo(r.traceback, err=True, nl=False)

    for r in work.skipped:
        done(r)
    start = time.perf_counter()
    if scheduler is not None:
        from magcal_cli.batch.dask import run_dask

        reports, seen = run_dask(work.jobs, scheduler, done)
        runner = Runner("dask", seen, scheduler)
    else:
        from magcal_cli.batch.run import run_local

        reports, runner = run_local(work.jobs, workers, done), Runner("local", workers)
    wall = time.perf_counter() - start
    by_log = {r.log: r for r in (*work.skipped, *reports)}
    ordered = [by_log[log] for log in work.order if log in by_log]
    click.echo(document(ordered, wall, runner, outdir) if as_json else table(ordered, wall, runner), nl=False)
    code = exit_code(ordered)
    if code:
        bad = [r for r in ordered if (r.exit_code not in (0, 3) if code == 1 else r.exit_code == 3)]
        click.echo(f"Error: batch: {len(bad)} of {len(ordered)} logs {'could not be fitted' if code == 1 else 'failed a --fail-on gate'}"
                   f" ({', '.join(r.name for r in bad[:5])}{', ...' if len(bad) > 5 else ''}). Their errors are in the "
                   f"summary and in {outdir}/<log>/batch.json", err=True)
        ctx.exit(code)


def main() -> None:
    """Console entry point. numpy's RuntimeWarnings on degenerate data stay off stderr, where an error is one
    line (the fuzz tests, which call `cli`, still see and fail on them)."""
    warnings.filterwarnings("ignore", category=RuntimeWarning)
    cli(prog_name="magcal")
