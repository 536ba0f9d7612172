"""The mismatch diagnosis of one magnetometer's joint MAP fit: compare, choose the physics, validate, explain.

Stages (mismatch.md section 3): the base fit is compared with replicates simulated from itself (ppc.py); every
registered effect the log can test is screened, the best are refitted and validated on held-out data
(select.py); the comparison is repeated with the accepted effects (`ppc_after`); a paragraph says what was
found in plain words (summary.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any, cast

import numpy as np

from magcal_cli import effects as registry
from magcal_cli.diagnose import ppc
from magcal_cli.diagnose.select import Selection, select
from magcal_cli.diagnose.summary import paragraph
from magcal_cli.errors import InsufficientDataError
from magcal_cli.models.map.estimate import MapEstimate
from magcal_cli.models.map.fit import fit_map
from magcal_cli.models.map.start import start_on
from magcal_cli.models.problem import Problem
from magcal_cli.progress import Hook, active, current
from magcal_cli.streams import Stream

#: magnetometer readings beyond which the diagnosis runs on every k-th one
DIAGNOSIS_EPOCHS = 12_000


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """One magnetometer's diagnosis: the final estimate (with every candidate's verdict as its effects) and
    the document's `diagnosis` block for it."""

    estimate: MapEstimate
    block: dict[str, Any]


def diagnose(problem: Problem, mag: Stream, base: MapEstimate, declination: float = 0.0, loss: str = "l2",
             dip_prior: float | None = None, replicates: int = ppc.REPLICATES, progress: Hook | None = None
             ) -> Diagnosis:
    """Diagnose the base fit `base` of `mag` (which must carry its context) against every registered effect.

    A log with more than DIAGNOSIS_EPOCHS magnetometer readings is diagnosed on every k-th reading (the tests
    have power to spare there, and the diagnosis costs some twenty fits); the effects it accepts are then
    fitted on every reading. `progress` defaults to the current hook (models.map calls this without one).
    """
    hook = progress or current()
    # readings, not epochs: a long log's epochs average several readings each (models/epochs.py), and thinning by
    # its epochs diagnosed an hour's flight on three times DIAGNOSIS_EPOCHS readings
    groups = None if base.context is None else base.context.ep.groups
    readings = base.epochs.size if groups is None else groups.t.size
    step = int(np.ceil(readings / DIAGNOSIS_EPOCHS))
    thin = mag if step <= 1 else Stream(mag.kind, mag.id, mag.t[::step], mag.values[::step], mag.source,
                                        mag.native_unit)
    if step > 1:
        hook(f"{mag.id} diagnosis: fitting every {step}th reading", 0)
    start = base if step <= 1 else _thinned(problem, thin, base, loss, dip_prior, declination)
    before = ppc.check(problem, thin, start, replicates, progress=hook, stage="replicates of the base model")
    candidates = tuple(e for e in registry.EFFECTS
                       if e not in problem.base_effects and registry.get(e).applies(problem.aux))
    def after_check(est: MapEstimate, modelled: tuple[str, ...]) -> ppc.Check:
        return ppc.check(problem, thin, est, replicates, stage=f"replicates with {', '.join(modelled)}")

    def on_all(est: MapEstimate, modelled: tuple[str, ...]) -> MapEstimate:
        # from the base fit, with the effects as the thinned fit found them: their slow directions (a lag against
        # a lever arm) took BROAD 06's fit from zero 2x the iterations
        assert base.context is not None and est.context is not None
        return fit_map(problem, mag, loss, dip_prior, effects=modelled, declination=declination,
                       warm=base.context.with_effects_of(est.context))

    def fitted_ids(est: MapEstimate) -> tuple[str, ...]:
        return tuple(f.id for f in est.effects if f.estimate is not None and f.id not in problem.base_effects)

    def ahead(est: MapEstimate) -> list[Callable[[], object]]:
        # what follows if the held-out check confirms the forward selection's model (nearly always): the fit on
        # every reading first, the longest item
        ids = fitted_ids(est)
        return [*([partial(on_all, est, ids)] if step > 1 else []), partial(after_check, est, ids)]

    sel: Selection = select(problem, thin, start, candidates, declination, loss, dip_prior, hook, ahead)
    modelled = tuple(v.id for v in sel.verdicts if v.status in ("accepted", "ambiguous") and v.estimate is not None)
    made_for, outcomes = sel.ahead
    ran = made_for is sel.estimate and fitted_ids(made_for) == modelled       # the check confirmed that model
    with active(hook):
        after = (cast(ppc.Check, outcomes[-1].get()) if ran else after_check(sel.estimate, modelled)) \
            if modelled else before
    est, full = replace(sel.estimate, effects=sel.verdicts), sel.estimate
    if step > 1:
        note = f"{mag.id}: diagnosed on every {step}th of {readings} readings; effects fitted on all"
        if modelled and not ran:
            hook(f"{mag.id} diagnosis: fitting {', '.join(modelled)} on every reading", 0)
        with active(hook):
            full = (cast(MapEstimate, outcomes[0].get()) if ran else on_all(sel.estimate, modelled)) \
                if modelled else base
        fitted = {f.id: f for f in full.effects}
        verdicts = tuple(replace(v, estimate=fitted[v.id].estimate, statistic=fitted[v.id].statistic,
                                 p_value=fitted[v.id].p_value) if v.id in fitted else v for v in sel.verdicts)
        est = replace(full, effects=verdicts, notes=(*full.notes, note))
        sel = replace(sel, verdicts=verdicts)                 # the paragraph quotes the values fitted on all
    # the effects every fit modelled (Problem.base_effects) stay in the document beside the diagnosis' verdicts
    forced = tuple(f for f in full.effects if f.id in problem.base_effects)
    est = replace(est, effects=(*forced, *est.effects))
    block: dict[str, Any] = {"sensor": mag.id, "ppc": before.document(), "located": before.located(mag.id)}
    if sel.heldout is not None:
        lo, hi = sel.heldout.ci95()
        block["heldout"] = {"protocol": sel.heldout.protocol, "rms_before_si": sel.heldout.rms_before,
                            "rms_after_si": sel.heldout.rms_after, "nll_gain_per_reading_ci95": [lo, hi],
                            "blocks": int(sel.heldout.gain.size)}
    block["ppc_after"] = after.document()
    block["summary"] = paragraph(mag.id, sel, before, after, mag.native_unit)
    return Diagnosis(est, block)


def _thinned(problem: Problem, thin: Stream, base: MapEstimate, loss: str, dip_prior: float | None,
             declination: float) -> MapEstimate:
    """The base model fitted on every k-th reading, starting from the fit on all of them (BROAD 06: 0.61 -> 0.2 s),
    or from scratch when that start does not stand."""
    assert base.context is not None
    try:
        return fit_map(problem, thin, loss, dip_prior, declination=declination,
                       warm=start_on(problem, base.context, thin))
    except (InsufficientDataError, np.linalg.LinAlgError):
        return fit_map(problem, thin, loss, dip_prior, declination=declination)
