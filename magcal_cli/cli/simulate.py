"""`magcal simulate`: a synthetic log with known truth, in any format magcal reads."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import click

from magcal_cli import __version__
from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity


def _effect_help() -> str:
    """The --effects help: syntax, units and every id with its keys."""
    from magcal_cli.synth.effects import syntax

    return ("Inject physical effects, repeatable and comma-separated: ID[:key=value,...]. Vectors are x/y/z "
            "(e.g. c_uT_per_A=0.2/-0.1/0.3), windows t0-t1/t0-t1 in s; omitted keys take their defaults. "
            f"Ids (keys): {syntax()}. See docs/simulate-effects.md.")


def _positive(_: click.Context, __: click.Parameter, value: float | None) -> float | None:
    """--duration, --rate, --mag-rate: a finite number > 0, or a usage error (exit 2)."""
    if value is not None and not (math.isfinite(value) and value > 0):
        msg = f"expected a finite number > 0, got {value:g}"
        raise click.BadParameter(msg)
    return value


class OldOut(click.Argument):
    """The positional OUT of old scripts: still read, left out of the usage line (-o/--output replaces it)."""

    def get_usage_pieces(self, ctx: click.Context) -> list[str]:
        return []


def _old_out(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
    """The positional OUT: the same as -o, with a deprecation note."""
    if value is not None:
        options.deprecated(ctx, f"the positional OUT is deprecated: write magcal simulate -o {value}")
    return options.log_output(ctx, param, value)


@click.command(context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("old_out", cls=OldOut, required=False, type=click.Path(path_type=Path), callback=_old_out)
@options.option("log-output", " (.mcap, .bag, .bin, .ulg, .csv, or no extension for a ROS 2 bag folder)")
@click.option("--scenario", type=click.Choice(["paper", "handheld", "multirotor", "rover"]), default="handheld",
              show_default=True,
              help="paper: the Huang et al. 2025 rotation protocol; handheld: still poses between hand rotations; "
                   "multirotor: 300 s flight (tilt within about 20 deg, full yaw turns, accelerating, GPS logged; "
                   "100/50 Hz); rover: 300 s drive (circles, figure-eights, tilt within 5 deg, GPS; 100/50 Hz). "
                   "See docs/simulate-scenarios.md.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seed of the truth, trajectory and noise (an integer >= 0).")
@click.option("--duration", type=float, default=None, callback=_positive,
              help="Length in seconds [default: the scenario's own; multirotor at least 90, rover 60].")
@click.option("--rate", type=float, default=None, callback=_positive,
              help="IMU rate in Hz [default: paper 80, handheld 100].")
@click.option("--mag-rate", type=float, default=None, callback=_positive,
              help="Magnetometer rate in Hz, any positive rate (a .csv needs one that divides --rate) "
                   "[default: paper 80, handheld 50].")
@click.option("--mag-phase", type=float, default=None, metavar="SECONDS",
              help="Time of the first magnetometer stamp after the first IMU stamp, >= 0 and below one "
                   "magnetometer period [default: drawn from --seed in 0-5 ms, as real boards stamp it; 0 for a "
                   ".csv, which holds one row per IMU sample].")
@options.option("inject", _effect_help())
@options.alias("--effect", "old_effects", "the same as --effects.", multiple=True, metavar="ID[:key=value,...]",
               callback=options.injected_effects)
@click.option("--vehicle-file", "vehicle_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="A vehicle file (JSON) setting this flight's compass: sysid, start_utc, hard_iron_uT, soft_iron, "
                   "orientation_deg, interference_uT_per_A (each optional; see docs/fleet.md). A fleet simulation "
                   "writes one per flight.")
@click.option("--truth", "truth_path", type=click.Path(path_type=Path), default=None,
              help="Where to write the truth [default: the log's name + .truth.json].")
@options.force()
@verbosity
@click.pass_context
@handle_errors
def simulate(ctx: click.Context, old_out: Path | None, out: Path | None, scenario: str, seed: int,
             duration: float | None, rate: float | None, mag_rate: float | None, mag_phase: float | None,
             effects: tuple[Any, ...], old_effects: tuple[Any, ...], vehicle_file: Path | None, truth_path: Path | None,
             force: bool) -> None:
    """Write a synthetic log (-o LOG; its extension picks the format) and its truth as a calibration document.

    The IMU samples the way the format defines (instantaneous, or the mean over the last IMU period in a .ulg);
    the magnetometer has its own rate and phase. The truth lists the injected effects in the log's magnetometer
    unit and with the reader's channel ids.
    """
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.calibration.document import dumps_json
    from magcal_cli.calibration.run import utc_now
    from magcal_cli.readers import open_recording
    from magcal_cli.synth.logs import imu_sampling, write_log
    from magcal_cli.synth.simulate import rates as run_rates
    from magcal_cli.synth.simulate import simulate as run_simulation
    from magcal_cli.synth.simulate import truth_calibration
    from magcal_cli.synth.vehicle import flight as vehicle_flight

    out = _log_path(ctx, old_out, out)
    effects = _all_effects(ctx, (*effects, *old_effects))
    truth_path = truth_path or out.with_name(out.name + ".truth.json")
    guards.log_extension(out, "'-o' / '--output'" if old_out is None else "OUT")
    _duration(scenario, duration)
    mag_phase = _mag_phase(out, scenario, rate, mag_rate, mag_phase)
    guards.refuse_existing((out, truth_path), force)
    for p in (out, truth_path):
        check_writable(p.parent, hint="Choose another path")
    say(ctx, f"simulating {scenario} (seed {seed})" + (f" with {', '.join(e.id for e in effects)}"
                                                             if effects else ""))
    vehicle = _vehicle(vehicle_file, effects)
    rates_hz = run_rates(scenario, rate, mag_rate)
    sim = run_simulation(scenario, seed, rate, mag_rate, duration, truth=vehicle.truth(seed, *rates_hz),
                         effects=(*effects, *vehicle.effects()), imu_sampling=imu_sampling(out),
                         mag_phase_s=mag_phase, truth_noise=True)
    sim = vehicle_flight(sim, vehicle)
    write_log(sim, out)
    written = open_recording(out)                       # the truth uses the ids and unit readers report
    write_text(truth_path, dumps_json(truth_calibration(sim, written, __version__, utc_now())))
    click.echo(f"wrote {out}")
    click.echo(f"wrote {truth_path}")


def _log_path(ctx: click.Context, old_out: Path | None, out: Path | None) -> Path:
    """The log to write: -o/--output, or the positional OUT of old scripts (with a deprecation note)."""
    if old_out is not None and out is not None:
        msg = f"give the log once: -o {out} (the positional {old_out} is the old spelling of -o)"
        raise click.UsageError(msg)
    if old_out is not None:
        return old_out
    if out is None:
        msg = "give the log to write with -o LOG, e.g. magcal simulate -o sim.bin"
        raise click.UsageError(msg)
    return out


def _all_effects(ctx: click.Context, specs: tuple[Any, ...]) -> tuple[Any, ...]:
    """--effects and the old --effect together, each effect once (a usage error otherwise)."""
    from magcal_cli.synth.effects import EffectSpecError, check_unique

    try:
        check_unique(specs)
    except EffectSpecError as exc:
        raise click.BadParameter(str(exc), ctx, param_hint="'--effects'") from None
    return specs


def _vehicle(path: Path | None, effects: tuple[Any, ...]) -> Any:
    """The --vehicle file (an empty Vehicle without it); interference set both ways is a usage error."""
    from magcal_cli.synth.vehicle import Vehicle, load

    if path is None:
        return Vehicle()
    vehicle = load(path)
    if vehicle.effects() and any(e.id == "current_interference" for e in effects):
        msg = f"{path} sets interference_uT_per_A and --effects has current_interference: give it once"
        raise click.BadParameter(msg, param_hint="'--vehicle'")
    return vehicle


def _duration(scenario: str, duration: float | None) -> None:
    """A flight or drive shorter than its scenario's phases: a usage error (exit 2) before simulating."""
    from magcal_cli.synth.scenarios import MIN_DURATION

    least = MIN_DURATION.get(scenario)
    if duration is not None and least is not None and duration < least:
        msg = (f"the {scenario} scenario needs --duration >= {least:g} s (its still, start and stop phases alone "
               f"take most of that), got {duration:g}")
        raise click.BadParameter(msg, param_hint="'--duration'")


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
