"""`magcal simulate`: a synthetic log with known truth, in any format magcal reads."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from magcal_cli import __version__
from magcal_cli.cli import options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity


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


@click.command(context_settings=CONTEXT, epilog=EXIT_CODES)
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
@options.force()
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
    from magcal_cli.calibration.run import utc_now
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
    say(ctx, f"simulating {scenario} (seed {seed})" + (f" with {', '.join(e.id for e in effects)}"
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
