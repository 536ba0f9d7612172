"""`magcal export`: firmware parameters from a calibration document."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity
from magcal_cli.errors import MagcalError

#: log formats that carry the vehicle's parameters, which `export` reads from a document's source log
PARAM_FORMATS = ("dataflash", "ulog")
#: the document's log format -> the firmware -o writes for (the flight controller that wrote the log)
FIRMWARE_OF = {"dataflash": "ardupilot", "ulog": "px4", "px4log": "px4"}
#: the --driver names (firmware.drivers.DRIVERS; the registry holds import strings, so this import is light)
DRIVER_NAMES = ("generic", "microstrain_inertial_driver", "phidgets_spatial")
#: the compass slots --slot takes: ArduPilot COMPASS_*, COMPASS_*2, COMPASS_*3; PX4 CAL_MAG0_* to CAL_MAG3_*
SLOTS = {"ardupilot": (1, 3), "px4": (0, 3)}


def _vehicle_params(ctx: click.Context, params_path: Path | None, cal_path: Path, cal: Any) -> dict[str, float]:
    """--params (a parameter file or a log), else the document's source log; refused when that log is missing
    but would have held the parameters (the export would silently differ)."""
    from magcal_cli.firmware.flown import load_params

    if params_path is not None:
        return load_params(params_path)
    source = cal.source.path
    src = Path(source)
    if source and src.is_file():
        say(ctx, f"vehicle parameters from the document's source log {src.name}")
        try:
            return load_params(src)
        except MagcalError as exc:
            say(ctx, f"warning: {exc}")
    elif source and cal.source.format in PARAM_FORMATS:
        msg = (f"{cal_path}: the source log {src} is missing, so the vehicle's parameters (compass slots, "
               "orientations, device ids) are unknown and the parameters would differ. Restore the log, or pass "
               "--params with the log or the vehicle's parameter file")
        raise MagcalError(msg)
    return {}


@click.command("export", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@options.option("output", help="Write the parameters of the flight controller whose log was calibrated (ArduPilot "
                               "for a DataFlash log, PX4 for a ULog or .px4log) to this file ('-': standard output).")
@click.option("--ardupilot", "ardupilot_out", type=click.Path(dir_okay=False, allow_dash=True, path_type=Path),
              default=None, metavar="FILE|-",
              help="Write ArduPilot COMPASS_* parameters to this file (Mission Planner NAME,VALUE; '-': standard "
                   "output), whatever log the calibration came from.")
@click.option("--px4", "px4_out", type=click.Path(dir_okay=False, allow_dash=True, path_type=Path), default=None,
              metavar="FILE|-",
              help="Write PX4 CAL_MAGn_* parameters to this file (QGroundControl .params; '-': standard output), "
                   "whatever log the calibration came from.")
@click.option("--driver", type=click.Choice(sorted(DRIVER_NAMES)), default=None,
              help="Write the parameter file this IMU driver loads to -o (one magnetometer: --mag when the document "
                   "has several): phidgets_spatial (ROS 2 cc_* parameters), microstrain_inertial_driver (hard-iron "
                   "offset and soft-iron matrix), generic (hard_iron / soft_iron, m = S (y - h)).")
@click.option("--style", type=click.Choice(["default", "mavproxy", "nsh"]), default="default", show_default=True,
              help="default: Mission Planner .param / QGroundControl .params; mavproxy: 'NAME VALUE' lines "
                   "(ArduPilot); nsh: 'param set NAME VALUE' lines (PX4).")
@options.mag("export")
@click.option("--slot", type=int, default=None,
              help="Parameter slot for one --mag: ArduPilot 1-3, PX4 0-3 [default: from the device ids].")
@options.option("params", help="The vehicle's parameters (.param/.params file or a log): slots, orientations, "
                               "features [default: the document's source log, if it exists].")
@click.option("--rotation", type=click.Choice(["auto", "enum", "custom"]), default="auto", show_default=True,
              help="External compasses: the nearest orientation enum, custom Euler angles, or auto (custom when "
                   "the enum misses by more than --custom-above-deg and the firmware has custom rotations).")
@click.option("--custom-above-deg", type=float, default=1.0, show_default=True,
              help="With --rotation auto: use a custom rotation when the nearest enum misses by more than this.")
@click.option("--external/--internal", default=None,
              help="Treat the compass as external/internal when the vehicle parameters do not say "
                   "[default: internal].")
@options.force()
@verbosity
@click.pass_context
@handle_errors
def export_cmd(ctx: click.Context, calibration: Path, out: Path | None, ardupilot_out: Path | None,
               px4_out: Path | None, driver: str | None, style: str, mags: tuple[str, ...], slot: int | None, params_path: Path | None,
               rotation: str, custom_above_deg: float, external: bool | None, force: bool) -> None:
    """Write firmware parameters for the calibration in CALIBRATION (a magcal document).

    -o writes the parameters of the flight controller that recorded the calibrated log; --ardupilot and --px4
    name the firmware (both at once write two files); --driver NAME -o FILE writes what an IMU driver loads.
    '-' writes to standard output.
    """
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.firmware.common import Options
    from magcal_cli.firmware.export import export
    from magcal_cli.firmware.paramfile import render

    targets = [(fw, path) for fw, path in (("ardupilot", ardupilot_out), ("px4", px4_out)) if path is not None]
    if driver is not None:
        if targets or slot is not None or params_path is not None:
            msg = "--driver writes one IMU driver's file to -o; leave out --ardupilot, --px4, --slot and --params"
            raise click.UsageError(msg)
        _driver_export(ctx, calibration, driver, out, mags, force)
        return
    if out is not None and targets:
        msg = ("give -o (the firmware of the calibrated log) or --ardupilot/--px4 (a firmware by name), not both")
        raise click.UsageError(msg)
    if out is None and not targets:
        msg = ("give -o FILE (the parameters of the firmware that wrote the calibrated log), or --ardupilot "
               "OUT.param or --px4 OUT.params; '-' writes to standard output")
        raise click.UsageError(msg)
    if sum(guards.is_stdout(path) for _, path in targets) > 1:
        msg = "only one of --ardupilot and --px4 can write to standard output ('-')"
        raise click.UsageError(msg)
    if slot is not None and len(mags) > 1:
        msg = f"--slot applies to one magnetometer, but --mag gives {len(mags)} ({', '.join(mags)}); give one --mag"
        raise click.UsageError(msg)
    cal = guards.calibration_document(calibration, "CALIBRATION", "Run: magcal export CAL.json -o OUT.param "
                                      "(or --ardupilot OUT.param, --px4 OUT.params); a log with the vehicle's "
                                      "parameters goes to --params")
    if out is not None:
        targets = [(_firmware_of(calibration, cal), out)]
    kinds = {fw: {"default": "mission-planner" if fw == "ardupilot" else "qgc"}.get(style, style) for fw, _ in targets}
    for firmware, kind in kinds.items():
        if (firmware, kind) in (("ardupilot", "nsh"), ("px4", "mavproxy")):
            msg = f"{style} is not a {firmware} parameter format"
            raise click.BadParameter(msg, param_hint="--style")
    guards.mags_in(mags, [m.id for m in cal.magnetometers], f"the calibration {calibration}")
    for firmware, _ in targets:
        first, last = SLOTS[firmware]
        if slot is not None and not first <= slot <= last:
            msg = f"{firmware} has no slot {slot}; give --slot {first} to {last} (or leave it out: the device ids decide)"
            raise click.BadParameter(msg, param_hint="'--slot'")
    files = [path for _, path in targets if not guards.is_stdout(path)]
    guards.refuse_existing(files, force)
    for path in files:
        check_writable(path.parent, hint="Choose another output file")
    params = _vehicle_params(ctx, params_path, calibration, cal)
    opts = Options(rotation, custom_above_deg, external, slot)
    stdout = any(guards.is_stdout(path) for _, path in targets)
    for firmware, path in targets:
        exp = export(cal, firmware, params, opts, list(mags) or None)
        for line in exp.notes + exp.warnings + exp.not_held:
            say(ctx, line)
        text = render(exp.params, kinds[firmware], exp.header(), exp.integers)
        if not guards.is_stdout(path):
            write_text(path, text)
        # results on stdout, unless the parameters themselves go there: then the rest is a remark on stderr
        lines = [m.lost_text() for m in exp.mags] + ([] if guards.is_stdout(path) else [f"wrote {path}"])
        for line in lines:
            if stdout:
                say(ctx, line)
            else:
                click.echo(line)
        if guards.is_stdout(path):
            click.echo(text, nl=False)


def _firmware_of(cal_path: Path, cal: Any) -> str:
    """The firmware whose parameters -o writes: that of the flight controller that wrote the calibrated log."""
    firmware = FIRMWARE_OF.get(cal.source.format)
    if firmware is None:
        msg = (f"{cal_path}: its log ({cal.source.format or 'of unknown format'}) was not written by a flight "
               "controller, so -o does not know which firmware's parameters to write; give --ardupilot FILE or "
               "--px4 FILE instead")
        raise click.UsageError(msg)
    return firmware


def _driver_export(ctx: click.Context, cal_path: Path, driver: str, out: Path | None, mags: tuple[str, ...],
                   force: bool) -> None:
    """--driver NAME -o FILE: one magnetometer's correction as the file that IMU driver loads."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.firmware.drivers import export_driver

    if out is None:
        msg = f"--driver {driver} needs -o FILE (e.g. -o params.yaml; '-' writes to standard output)"
        raise click.UsageError(msg)
    cal = guards.calibration_document(cal_path, "CALIBRATION", f"Run: magcal export CAL.json --driver {driver} "
                                      "-o params.yaml")
    refused = [str(r.get("id")) for r in cal.refused]
    guards.mags_in([m for m in mags if m not in refused], [m.id for m in cal.magnetometers],
                   f"the calibration {cal_path}")
    if not guards.is_stdout(out):
        guards.refuse_existing([out], force)
        check_writable(out.parent, hint="Choose another output file")
    result = export_driver(cal, driver, mags)
    for line in result.not_held:
        say(ctx, f"{result.mag_id}: {line}")
    if guards.is_stdout(out):
        click.echo(result.text, nl=False)
        return
    write_text(out, result.text)
    click.echo(f"wrote {out} ({driver}, {result.mag_id})")
