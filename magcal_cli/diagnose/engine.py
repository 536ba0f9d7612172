"""The mismatch diagnosis of one magnetometer's joint MAP fit: compare, choose the physics, validate, explain.

Stages (mismatch.md section 3): the base fit is compared with replicates simulated from itself (ppc.py); every
registered effect the log can test is screened, the best are refitted and validated on held-out data
(select.py); the comparison is repeated with the accepted effects (`ppc_after`); a paragraph says what was
found in plain words (summary.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from .. import effects as registry
from ..models.map import MapEstimate
from ..models.problem import Problem
from ..streams import Stream
from . import ppc
from .select import Selection, select
from .summary import paragraph


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """One magnetometer's diagnosis: the final estimate (with every candidate's verdict as its effects) and
    the document's `diagnosis` block for it."""

    estimate: MapEstimate
    block: dict[str, Any]


def diagnose(problem: Problem, mag: Stream, base: MapEstimate, declination: float = 0.0, loss: str = "l2",
             dip_prior: float | None = None, replicates: int = ppc.REPLICATES) -> Diagnosis:
    """Diagnose the base fit `base` of `mag` (which must carry its context) against every registered effect."""
    before = ppc.check(problem, mag, base, replicates)
    sel: Selection = select(problem, mag, base, tuple(registry.EFFECTS), declination, loss, dip_prior)
    est = replace(sel.estimate, effects=sel.verdicts)
    accepted = [v for v in sel.verdicts if v.status in ("accepted", "ambiguous") and v.estimate is not None]
    after = ppc.check(problem, mag, sel.estimate, replicates) if accepted else before
    block: dict[str, Any] = {"sensor": mag.id, "ppc": before.document(), "located": before.located(mag.id)}
    if sel.heldout is not None:
        lo, hi = sel.heldout.ci95()
        block["heldout"] = {"protocol": sel.heldout.protocol, "rms_before_si": sel.heldout.rms_before,
                            "rms_after_si": sel.heldout.rms_after, "nll_gain_per_reading_ci95": [lo, hi],
                            "blocks": int(sel.heldout.gain.size)}
    block["ppc_after"] = after.document()
    block["summary"] = paragraph(mag.id, sel, before, after, mag.native_unit)
    return Diagnosis(est, block)
