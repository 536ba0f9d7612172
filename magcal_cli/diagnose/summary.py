"""The diagnosis in one paragraph a pilot understands: what disagreed, what physics was added, how much it helped."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from magcal_cli import effects as registry
from magcal_cli import units
from magcal_cli.models.result import EffectFit

if TYPE_CHECKING:
    from magcal_cli.diagnose.ppc import Check
    from magcal_cli.diagnose.select import Selection

#: short display names of the field units
SHORT = {"tesla": "T", "gauss": "G", "milligauss": "mG", "microtesla": "uT", "nanotesla": "nT"}
#: the smallest p-value a table prints as a number: below it the tail approximations behind it (chi-squared, Gumbel)
#: are not accurate, and a double cannot tell 1 - p from 1 (R's format.pval uses the same floor)
P_FLOOR = 1e-16
#: the paragraph's floor: the simulation check runs a few dozen replicates, so a smaller p is an extrapolation
P_FLOOR_PEOPLE = 0.001
#: a paragraph's sentence on an effect the log cannot test, with the space before it (`fold`)
UNTESTABLE = re.compile(r" \S+ is not testable in this log: .*?\.(?= [A-Z]| \S+ is not testable|$)")


def p_text(p: float | None, floor: float = P_FLOOR) -> str:
    """A p-value for a table cell: '0.032', '< 1e-16' below `floor` (a p of 0 included), 'n/a' when missing."""
    if p is None or not math.isfinite(p):
        return "n/a"
    return f"< {floor:g}" if p < floor else f"{p:.2g}"


def p_is(p: float | None, floor: float = P_FLOOR) -> str:
    """A p-value in a sentence: 'p = 0.032', 'p < 1e-16' or 'p n/a'."""
    text = p_text(p, floor)
    return f"p {text}" if text.startswith("<") or text == "n/a" else f"p = {text}"


def unit_suffix(unit: str | None) -> str:
    """' <unit>' after a number; nothing for a dimensionless one ('1', '') or a missing one."""
    return "" if not unit or unit == "1" else f" {unit}"


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
        parts.append(f"{b.name} = {text}{unit_suffix(u)}")
    return "; ".join(parts)


def separate(eid: str, rivals: Sequence[str]) -> str:
    """The sentence on an effect this log cannot tell apart from its rivals, and the recording that would."""
    return (f"This log cannot tell {eid} apart from {' or '.join(rivals)}; to separate them, record "
            f"{registry.get(eid).separating_experiment}.")


def _advice(eid: str) -> str:
    """The separating half of `separate`: said once for all magnetometers (`fold`)."""
    return f"; to separate them, record {registry.get(eid).separating_experiment}."


def paragraph(sensor: str, sel: Selection, before: Check, after: Check, unit: str = "tesla") -> str:
    """One paragraph for one magnetometer."""
    unit = units.canonical(unit)
    found = [v for v in sel.verdicts if v.status == "accepted"]
    unclear = [v for v in sel.verdicts if v.status == "ambiguous"]
    untestable = [v for v in sel.verdicts if v.status == "not_testable"]
    mismatch = before.global_p < 0.01
    out = [f"{sensor}: " + (f"the recording disagrees with the calibrated model beyond its noise (simulation check "
                            f"{p_is(before.global_p, P_FLOOR_PEOPLE)}; largest: {before.top(1)[0][0]})." if mismatch
                            else f"the recording agrees with the calibrated model within its noise (simulation check "
                            f"{p_is(before.global_p, P_FLOOR_PEOPLE)}).")]
    for v in found:
        values = _values(v, unit)
        out.append(f"{registry.get(v.id).physics_left_out} Modelled as {v.id}" + (f": {values}." if values else "."))
    for v in unclear:
        said = separate(v.id, v.confounded_with) if v.confounded_with else f"{v.reason[:1].upper()}{v.reason[1:]}."
        out.append(f"{registry.get(v.id).physics_left_out} {said}"
                   + (" The fit could not carry either, so neither is modelled." if "not modelled" in v.reason else ""))
    if sel.heldout is not None and (found or unclear):
        f = units.from_si(unit)
        u = SHORT.get(unit, unit)
        out.append(f"On held-out readings the compass residual went from {sel.heldout.rms_before * f:.3g} to "
                   f"{sel.heldout.rms_after * f:.3g} {u}; the simulation check now gives "
                   f"{p_is(after.global_p, P_FLOOR_PEOPLE)}.")
    if not found and not unclear:
        out.append("No physics beyond the base model was needed" + (
            ": the remaining mismatch is not explained by any effect magcal can model"
            if mismatch else "") + ".")
    out += [f"{v.id} is not testable in this log: {v.reason}." for v in untestable]
    return " ".join(out)


def fold(paragraphs: Sequence[str]) -> list[str]:
    """The magnetometers' paragraphs with each explanation said once for all: a later paragraph drops an effect's
    physics sentence, the recording that separates it and a 'not testable' sentence an earlier one already gave
    (the first two come from the effect registry word for word)."""
    pieces = [p for eid in registry.EFFECTS for p in (f"{registry.get(eid).physics_left_out} ", _advice(eid))]
    said: set[str] = set()
    out = []
    for text in paragraphs:
        mine = {p for p in pieces if p in text} | set(UNTESTABLE.findall(text))
        for p in mine & said:
            text = text.replace(p, "." if p.startswith(";") else "")
        said |= mine
        out.append(text.strip())
    return out
