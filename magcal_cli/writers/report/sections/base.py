"""What a section of report.html is (`Section`) and what it renders from (`Context`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from magcal_cli.writers.report.sections.markup import anchor

if TYPE_CHECKING:
    from magcal_cli.calibration.run import RunResult
    from magcal_cli.calibration.types import MagCalibration
    from magcal_cli.writers.report.verdict import Group, Verdict


@dataclass(frozen=True, eq=False)
class Context:
    """What a section renders from: the run, its verdicts and findings; its anchor, link text and magnetometer."""

    result: RunResult
    verdicts: list[Verdict]
    groups: list[Group]
    anchor: str = ""
    title: str = ""
    mag: MagCalibration | None = None
    verdict: Verdict | None = None


@dataclass(frozen=True)
class Section:
    """One entry of report.html: its anchor, its link text and its renderer (None: nothing to show).

    A `per_magnetometer` section repeats for every magnetometer, anchored `<id>-<anchor of the magnetometer>` and
    linked by the magnetometer's id.
    """

    id: str
    title: str
    render: Callable[[Context], str | None]
    per_magnetometer: bool = False

    def contexts(self, page: Context) -> list[Context]:
        """The contexts this section renders in, in page order: one, or one per magnetometer."""
        if not self.per_magnetometer:
            return [replace(page, anchor=self.id, title=self.title)]
        mags = page.result.calibration.magnetometers
        return [replace(page, anchor=f"{self.id}-{anchor(m.id)}", title=m.id, mag=m, verdict=v)
                for m, v in zip(mags, page.verdicts, strict=True)]
