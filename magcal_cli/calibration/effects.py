"""An effect result as a calibration document's `effects[]` entry (calibration-file.md "Effects")."""

from __future__ import annotations

from typing import Any

import numpy as np

from magcal_cli import units
from magcal_cli.effects import get
from magcal_cli.models.result import EffectFit

#: two-sided 95 % normal quantile for ci95
Z95 = 1.959963984540054


def _plain(x: np.ndarray) -> Any:
    """A scalar for one-entry blocks, else a list."""
    return float(x[0]) if x.size == 1 else [float(v) for v in x]


def entry(fit: EffectFit, mag_unit: str | None) -> dict[str, Any]:
    """The document entry; field parameters in `mag_unit` (the log's native magnetometer unit)."""
    eff = get(fit.id)
    unit = units.canonical(mag_unit) if mag_unit else "tesla"
    factor = units.from_si(unit) if mag_unit else 1.0
    out: dict[str, Any] = {"id": fit.id, "sensor": fit.sensor, "status": fit.status,
                           "channels": list(fit.channels), "physics_left_out": eff.physics_left_out}
    if fit.status == "not_testable":
        out["physics_left_out"] = f"{eff.physics_left_out} Not testable in this log: {fit.reason}."
        out.update({"params": {}, "std": {}, "ci95": {}, "units": {}, "reason": fit.reason})
        return out
    params, std, ci, unit_of = {}, {}, {}, {}
    est = fit.estimate
    for b in eff.params if est is not None else ():
        assert est is not None
        f = factor if b.si_scale == "field" else (float(np.rad2deg(1.0)) if b.si_scale == "angle" else 1.0)
        v, s = est[b.name] * f, est.std(b.name) * f
        params[b.name], std[b.name] = _plain(v), _plain(s)
        ci[b.name] = [float(v[0] - Z95 * s[0]), float(v[0] + Z95 * s[0])] if v.size == 1 else \
            [[float(a - Z95 * e), float(a + Z95 * e)] for a, e in zip(v, s, strict=True)]
        unit_of[b.name] = eff.units[b.name].replace("{field}", unit)
    for k, v in fit.constants.items():
        if k.startswith("_"):                    # a term's private tables (e.g. a grid), not a result
            continue
        params[k] = v
        if k in eff.units:
            unit_of[k] = eff.units[k].replace("{field}", unit)
    kind = fit.test_kind if fit.estimate is not None or fit.test_kind != "wald" else "excluded readings"
    out.update({"params": params, "std": std, "ci95": ci, "units": unit_of,
                "test": {"kind": kind, "statistic": fit.statistic, "dof": fit.dof, "p_value": fit.p_value},
                "confounded_with": list(fit.confounded_with)})
    if fit.evidence:
        out["evidence"] = {(k[:-3] if k.endswith("_si") else k): (v * factor if k.endswith("_si") else v)
                           for k, v in fit.evidence.items()}
    if fit.reason:
        out["reason"] = fit.reason
    if fit.status == "ambiguous" and fit.confounded_with:
        rivals = " or ".join(fit.confounded_with)
        out["physics_left_out"] = (f"{eff.physics_left_out} This log cannot tell it apart from {rivals}; "
                                   f"to separate them, record {eff.separating_experiment}.")
    if eff.firmware:
        out["firmware"] = dict(eff.firmware)
    return out
