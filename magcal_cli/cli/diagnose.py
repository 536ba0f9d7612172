"""`magcal diagnose`: what physics the calibrated model leaves out of a log."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from magcal_cli.cli import options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, progress_line, verbosity
from magcal_cli.config import Config

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling


@click.command("diagnose", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@click.option("--calibration", "cal_path", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=None, help="A magcal calibration of this vehicle: its magnetometers and IMU are diagnosed "
                                 "[default: every magnetometer of the log].")
@click.option("-o", "--outdir", type=click.Path(path_type=Path), default=None,
              help="Also write diagnosis.json (the diagnosis and every effect's verdict) to this directory.")
@options.as_json("Print the diagnosis and the effects as one JSON document.")
@options.force("Overwrite an existing diagnosis.json.")
@options.fmt
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
    with progress_line(ctx) as progress:
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
