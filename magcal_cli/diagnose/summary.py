"""The diagnosis in one paragraph a pilot understands: what disagreed, what physics was added, how much it helped."""

from __future__ import annotations

from typing import TYPE_CHECKING

from magcal_cli import effects as registry
from magcal_cli import units
from magcal_cli.models.result import EffectFit

if TYPE_CHECKING:
    from magcal_cli.diagnose.ppc import Check
    from magcal_cli.diagnose.select import Selection

#: short display names of the field units
SHORT = {"tesla": "T", "gauss": "G", "milligauss": "mG", "microtesla": "uT", "nanotesla": "nT"}


def _values(fit: EffectFit, unit: str) -> str:
    """The fitted parameters in the magnetometer's unit, e.g. 'c = (1.8, -0.4, 2.6) mG/A'."""
    eff = registry.get(fit.id)
    if fit.estimate is None:
        return ""
    parts = []
    for b in eff.params:
        v = fit.estimate[b.name] * (units.from_si(unit) if b.si_scale == "field" else 1.0)
        u = eff.units[b.name].replace("{field}", SHORT.get(unit, unit)).replace("/ampere", "/A")
        text = f"{v[0]:.3g}" if v.size == 1 else "(" + ", ".join(f"{x:.3g}" for x in v) + ")"
        parts.append(f"{b.name} = {text}" + ("" if u == "1" else f" {u}"))
    return "; ".join(parts)


def _p(p: float) -> str:
    """A p-value for people."""
    return "< 0.001" if p < 0.001 else f"= {p:.2g}"


def paragraph(sensor: str, sel: Selection, before: Check, after: Check, unit: str = "tesla") -> str:
    """One paragraph for one magnetometer."""
    unit = units.canonical(unit)
    found = [v for v in sel.verdicts if v.status == "accepted"]
    unclear = [v for v in sel.verdicts if v.status == "ambiguous"]
    untestable = [v for v in sel.verdicts if v.status == "not_testable"]
    mismatch = before.global_p < 0.01
    out = [f"{sensor}: " + (f"the recording disagrees with the calibrated model beyond its noise (simulation check "
                            f"p {_p(before.global_p)}; largest: {before.top(1)[0][0]})." if mismatch else
                            f"the recording agrees with the calibrated model within its noise (simulation check "
                            f"p {_p(before.global_p)}).")]
    for v in found:
        eff = registry.get(v.id)
        out.append(f"{eff.physics_left_out} Modelled: {_values(v, unit)}.")
    for v in unclear:
        eff = registry.get(v.id)
        out.append(f"{eff.physics_left_out} ({v.reason}; to separate them, record {eff.separating_experiment}).")
    if sel.heldout is not None and (found or unclear):
        f = units.from_si(unit)
        u = SHORT.get(unit, unit)
        out.append(f"On held-out readings the compass residual went from {sel.heldout.rms_before * f:.3g} to "
                   f"{sel.heldout.rms_after * f:.3g} {u}; the simulation check now gives p {_p(after.global_p)}.")
    if not found and not unclear:
        out.append("No physics beyond the base model was needed" + (
            ": the remaining mismatch is not explained by any effect magcal can model"
            if mismatch else "") + ".")
    if untestable:
        out.append("Not testable in this log: " + "; ".join(f"{v.id} ({v.reason})" for v in untestable) + ".")
    return " ".join(out)

