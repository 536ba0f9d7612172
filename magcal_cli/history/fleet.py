"""The fleet: each vehicle's compasses over their flights, with the changes the detector found (`magcal fleet`).

A compass's state:
- `new`: fewer than 2 flights, nothing to compare;
- `changed`: a watched parameter alarmed at its latest flight (what CI should stop on);
- `settled`: it changed earlier and has been steady since;
- `steady`: never alarmed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcal_cli.history.detect import SLACK, THRESHOLD, cusum, inflation, standardised_differences
from magcal_cli.history.identity import SYSID_ONLY, identified_by
from magcal_cli.streams import FloatArray

#: the parameter groups change detection watches; `dip_deg` ("field") changes with the place and is only shown
WATCHED = ("hard_iron", "soft_iron", "orientation", "interference")
STATES = ("changed", "settled", "new", "steady")


def category(name: str) -> str:
    """The group of a parameter name: hard_iron, soft_iron, orientation, interference (an effect named so),
    effect (another effect) or field (dip)."""
    head = name.split(".", 1)[0]
    if head in ("hard_iron", "soft_iron", "orientation"):
        return head
    if head == "dip_deg":
        return "field"
    return "interference" if head.endswith("interference") else "effect"


@dataclass(frozen=True)
class Change:
    """A detected change of one parameter: the flights (indexes) it alarmed at and started at, and the step."""

    param: str
    category: str
    at: int
    start: int
    step: float
    z: float


@dataclass(frozen=True, eq=False)
class Compass:
    """One vehicle's compass: its flights in time order, every parameter's series (values, reported stds) and the
    changes found."""

    vehicle: str
    sensor: str
    unit: str
    flights: list[dict[str, Any]]
    series: dict[str, tuple[FloatArray, FloatArray]]
    changes: list[Change] = field(default_factory=list)

    @property
    def identified_by(self) -> str:
        """How its vehicle was identified, in words (each way its flights were, where they differ)."""
        return ", ".join(sorted({identified_by(f.get("vehicle_source", "")) for f in self.flights}))

    @property
    def sysid_only(self) -> bool:
        """Its vehicle is known by SYSID_THISMAV alone: other vehicles with that SYSID merge into its series."""
        return any(f.get("vehicle_source") == SYSID_ONLY for f in self.flights)

    @property
    def state(self) -> str:
        """new, changed, settled or steady (module docstring)."""
        if len(self.flights) < 2:
            return "new"
        if any(c.at == len(self.flights) - 1 for c in self.changes):
            return "changed"
        return "settled" if self.changes else "steady"

    def change_groups(self) -> list[tuple[int, int, list[Change]]]:
        """The changes grouped by the flight they alarmed at: (at, start, changes), in time order."""
        groups: dict[int, list[Change]] = {}
        for c in self.changes:
            groups.setdefault(c.at, []).append(c)
        return [(at, min(c.start for c in cs), cs) for at, cs in sorted(groups.items())]


@dataclass(frozen=True, eq=False)
class Fleet:
    """Every compass of the store, the std inflation per parameter and the detector's settings."""

    compasses: list[Compass]
    inflation: dict[str, float]
    slack: float = SLACK
    threshold: float = THRESHOLD

    def counts(self) -> dict[str, int]:
        """Compasses per state."""
        return {s: sum(c.state == s for c in self.compasses) for s in STATES}


def _series(flights: list[dict[str, Any]]) -> dict[str, tuple[FloatArray, FloatArray]]:
    """name -> (values, stds) over the flights (NaN where a flight lacks the parameter)."""
    names = sorted({n for f in flights for n in f["params"]})
    out = {}
    for n in names:
        pairs = [f["params"].get(n) or [None, None] for f in flights]
        out[n] = (np.array([np.nan if v is None else v for v, _ in pairs], dtype=np.float64),
                  np.array([np.nan if s is None else s for _, s in pairs], dtype=np.float64))
    return out


def build(entries: list[dict[str, Any]], slack: float = SLACK, threshold: float = THRESHOLD,
          scale: float | None = None) -> Fleet:
    """The fleet from store entries (store.load order): series per compass, inflation per parameter pooled over
    the fleet (or `scale` for all), and the CUSUM's changes of every watched parameter."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for e in entries:
        groups.setdefault((e["vehicle"], e["sensor"]), []).append(e)
    compasses = []
    for (vehicle, sensor), flights in groups.items():
        flights = sorted(flights, key=lambda f: (f["log_utc"] is None, f["log_utc"] or 0.0, f["path"]))
        compasses.append(Compass(vehicle, sensor, flights[-1]["unit"], flights, _series(flights)))
    pooled: dict[str, list[FloatArray]] = {}
    for c in compasses:
        for n, (x, s) in c.series.items():
            pooled.setdefault(n, []).append(standardised_differences(x, s))
    factors = {n: scale if scale is not None else inflation(np.concatenate(ds)) for n, ds in pooled.items()}
    out = []
    for c in compasses:
        changes = []
        for n, (x, s) in c.series.items():
            if category(n) in WATCHED:
                changes += [Change(n, category(n), a.at, a.start, a.step, a.z)
                            for a in cusum(x, s * factors[n], slack, threshold)]
        out.append(Compass(c.vehicle, c.sensor, c.unit, c.flights, c.series, sorted(changes, key=lambda a: a.at)))
    return Fleet(out, factors, slack, threshold)


def to_json(fleet: Fleet) -> dict[str, Any]:
    """The --json document."""
    def flight(f: dict[str, Any]) -> dict[str, Any]:
        return {k: f[k] for k in ("log_utc", "path", "sha256", "method", "quality")}

    return {"format": "magcal-fleet", "format_version": 1, "counts": fleet.counts(),
            "detector": {"method": "two-sided CUSUM on inverse-variance reference", "slack": fleet.slack,
                         "threshold": fleet.threshold, "watched": list(WATCHED)},
            "inflation": fleet.inflation,
            "compasses": [{"vehicle": c.vehicle, "identified_by": c.identified_by, "sysid_only": c.sysid_only,
                           "sensor": c.sensor, "unit": c.unit, "state": c.state,
                           "flights": [flight(f) for f in c.flights],
                           "changes": [{"param": ch.param, "category": ch.category, "alarm_flight": ch.at,
                                        "change_flight": ch.start, "alarm_log": c.flights[ch.at]["path"],
                                        "change_log": c.flights[ch.start]["path"], "step": ch.step, "z": ch.z}
                                       for ch in c.changes],
                           "series": {n: {"value": [None if np.isnan(v) else float(v) for v in x],
                                          "std": [None if np.isnan(v) else float(v) for v in s]}
                                      for n, (x, s) in c.series.items()}}
                          for c in fleet.compasses]}


def text(fleet: Fleet) -> str:
    """The text summary: one line per compass, then one per change."""
    counts = fleet.counts()
    lines = [f"{len(fleet.compasses)} compasses on {len({c.vehicle for c in fleet.compasses})} vehicles: "
             + ", ".join(f"{counts[s]} {s}" for s in STATES)]
    width = max([len(c.vehicle) for c in fleet.compasses] + [7])
    lines.append(f"{'VEHICLE':<{width}}  {'COMPASS':<22} {'FLIGHTS':>7}  {'STATE':<8} LAST CHANGE")
    for c in fleet.compasses:
        groups = c.change_groups()
        last = ""
        if groups:
            at, start, cs = groups[-1]
            cats = sorted({ch.category for ch in cs})
            last = (f"{', '.join(cats)} at flight {start + 1} ({c.flights[start]['path']}), "
                    f"alarm at {at + 1}")
        lines.append(f"{c.vehicle:<{width}}  {c.sensor:<22} {len(c.flights):>7}  {c.state:<8} {last}")
    return "\n".join(lines + _vehicles(fleet, width)) + "\n"


def _vehicles(fleet: Fleet, width: int) -> list[str]:
    """How each vehicle was identified, with a warning for those known by SYSID_THISMAV alone."""
    how: dict[str, str] = {}
    merged: set[str] = set()
    for c in fleet.compasses:
        how[c.vehicle] = c.identified_by
        merged |= {c.vehicle} if c.sysid_only else set()
    lines = ["", f"{'VEHICLE':<{width}}  IDENTIFIED BY", *(f"{v:<{width}}  {h}" for v, h in how.items())]
    lines += [f"warning: {v} is identified by SYSID_THISMAV only: vehicles sharing it merge into one series, and a "
              "compass change may be another vehicle's compass. Set BRD_SERIAL_NUM, or record with --vehicle"
              for v in sorted(merged)]
    return lines
