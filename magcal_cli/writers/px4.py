"""px4.params: CAL_MAGn_* parameters in QGroundControl's tab-separated layout (firmware.px4)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from magcal_cli.atomic import write_text
from magcal_cli.firmware.heading import parameter_file

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


class Px4Writer:
    """px4.params, for the vehicle whose log was calibrated (device ids pick the CAL_MAGn slots)."""

    name: ClassVar[str] = "px4"
    files: ClassVar[tuple[str, ...]] = ("px4.params",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Export every magnetometer the heading check passes on and write the file."""
        text = parameter_file(result.calibration, "px4", dict(result.recording.params), "qgc")
        return [write_text(outdir / self.files[0], text)]
