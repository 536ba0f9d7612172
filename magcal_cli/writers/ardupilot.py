"""ardupilot.param: COMPASS_* parameters in Mission Planner's NAME,VALUE layout (firmware.ardupilot)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from magcal_cli.atomic import write_text
from magcal_cli.firmware.heading import parameter_file

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult


class ArduPilotWriter:
    """ardupilot.param, for the vehicle whose log was calibrated (its parameters pick slots and rotations)."""

    name: ClassVar[str] = "ardupilot"
    files: ClassVar[tuple[str, ...]] = ("ardupilot.param",)

    def write(self, result: RunResult, outdir: Path) -> list[Path]:
        """Export every magnetometer the heading check passes on and write the file."""
        text = parameter_file(result.calibration, "ardupilot", dict(result.recording.params), "mission-planner")
        return [write_text(outdir / self.files[0], text)]
