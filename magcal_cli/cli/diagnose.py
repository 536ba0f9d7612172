"""`magcal diagnose`: what physics the calibrated model leaves out of a log."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from magcal_cli.cli import guards, options
from magcal_cli.cli.common import CONTEXT, EXIT_CODES, handle_errors, progress_line, verbosity

if TYPE_CHECKING:
    from magcal_cli.streams import Sampling


@click.command("diagnose", context_settings=CONTEXT, epilog=EXIT_CODES)
@click.argument("log", type=click.Path(exists=True, path_type=Path))
@options.option("calibration", help="A magcal calibration of this vehicle: its magnetometers and IMU are "
                                     "diagnosed [default: every magnetometer of the log].")
@options.mag("diagnose (with --calibration: some of its magnetometers)")
@options.option("outdir", help="Also write diagnosis.json (the diagnosis and every effect's verdict) to this "
                               "folder.")
@options.as_json("Print the diagnosis and the effects as one JSON document.")
@options.force("Overwrite an existing diagnosis.json.")
@options.window()
@options.fmt
@options.timing
@verbosity
@click.pass_context
@handle_errors
def diagnose_cmd(ctx: click.Context, log: Path, cal_path: Path | None, mags: tuple[str, ...], outdir: Path | None,
                 as_json: bool, force: bool, start_s: float | None, end_s: float | None, fmt: str | None,
                 imu_timing: Sampling | None, mag_timing: Sampling | None) -> None:
    """Find what physics the calibrated model leaves out of LOG, model it, and show the held-out improvement."""
    import json

    from magcal_cli.atomic import atomic_path, check_writable
    from magcal_cli.pipeline import calibrate, command_config, not_diagnosed

    guards.time_window(start_s, end_s)
    mag, imu = ",".join(mags) or "all", None
    if cal_path is not None:
        cal = guards.calibration_document(cal_path, "--calibration",
                                          "Give the calibration, or leave --calibration out")
        have = [m.id for m in cal.magnetometers]
        guards.mags_in(mags, have, f"the calibration {cal_path}")
        mag, imu = ",".join(mags or have), cal.imu.id
    target = None if outdir is None else outdir / "diagnosis.json"
    if outdir is not None and target is not None:
        guards.refuse_existing((target,), force, ", or choose another -o")
        check_writable(outdir, create=True, hint="Choose another -o")
    cfg = command_config(mag, imu, start_s=start_s, end_s=end_s, imu_timing=imu_timing,
                         mag_timing=mag_timing)               # what fit does by default
    with progress_line(ctx) as progress:
        result = calibrate(log, cfg, fmt, progress)
    skipped = not_diagnosed(result)
    doc = {"log": str(log.resolve()), "method": result.calibration.method, "diagnosis": result.calibration.diagnosis,
           "not_diagnosed": skipped, "effects": list(result.calibration.effects)}
    text = json.dumps(doc, indent=2, default=float) + "\n"
    if target is not None:
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tmp.write_text(text)
    if as_json:
        click.echo(text, nl=False)
        return
    everyone = [m.id for m in result.calibration.magnetometers]
    for f in result.findings:               # each magnetometer the diagnosis did not run for, by name
        if f.code == "diagnosis_skipped":
            click.echo(f"{', '.join(f.evidence.get('sensors', everyone))}: {f.message}")
    from magcal_cli.diagnose.summary import fold

    for text in fold([b["summary"] for b in (result.calibration.diagnosis or {}).get("sensors", [])]):
        click.echo(text)                    # each explanation once for all magnetometers
    if target is not None:
        click.echo(f"wrote {target}")
