"""`magcal export`: firmware parameters from a calibration document."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from magcal_cli.cli import options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, say, verbosity
from magcal_cli.errors import MagcalError

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
@click.option("--ardupilot", "ardupilot_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write ArduPilot COMPASS_* parameters to this file (Mission Planner NAME,VALUE).")
@click.option("--px4", "px4_out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write PX4 CAL_MAGn_* parameters to this file (QGroundControl .params).")
@click.option("--style", type=click.Choice(["default", "mavproxy", "nsh"]), default="default", show_default=True,
              help="default: Mission Planner .param / QGroundControl .params; mavproxy: 'NAME VALUE' lines "
                   "(ArduPilot); nsh: 'param set NAME VALUE' lines (PX4).")
@options.mag("export")
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
@options.force()
@verbosity
@click.pass_context
@handle_errors
def export_cmd(ctx: click.Context, calibration: Path, ardupilot_out: Path | None, px4_out: Path | None, style: str,
               mags: tuple[str, ...], slot: int | None, params_path: Path | None, rotation: str,
               custom_above_deg: float, external: bool | None, force: bool) -> None:
    """Write firmware parameters for the calibration in CALIBRATION (a magcal document)."""
    from magcal_cli.atomic import check_writable, write_text
    from magcal_cli.firmware.common import Options
    from magcal_cli.firmware.export import export
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
            say(ctx, line)
        for m in exp.mags:
            click.echo(m.lost_text())
        write_text(out, render(exp.params, kinds[firmware], exp.header(), exp.integers))
        click.echo(f"wrote {out}")
