"""Quality gates: the small expression language of `fit --fail-on` and `check --fail-on`.

    EXPR      := CONDITION ("," CONDITION)*
    CONDITION := METRIC OP NUMBER          e.g. heading_error_deg>5
    OP        := ">" | ">=" | "<" | "<="
    NUMBER    := a decimal number, optionally with an exponent (2, 0.5, 1e-3)

Each condition describes a failure. A magnetometer fails when any condition holds for it, or when a metric a
condition names could not be measured for it (what cannot be measured cannot pass a gate). The expression
is parsed with one regular expression per condition; nothing is evaluated as code.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from .errors import MagcalError

OPS: dict[str, Callable[[float, float], bool]] = {">": operator.gt, ">=": operator.ge, "<": operator.lt,
                                                  "<=": operator.le}
_CONDITION = re.compile(r"^\s*([a-z][a-z0-9_]*)\s*(>=|<=|>|<)\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$")


class GateSyntaxError(MagcalError):
    """A --fail-on expression that does not parse or names an unknown metric (a usage error)."""


@dataclass(frozen=True)
class Condition:
    """One failure condition: METRIC OP THRESHOLD."""

    metric: str
    op: str
    threshold: float

    def __str__(self) -> str:
        return f"{self.metric}{self.op}{self.threshold:g}"

    def holds(self, value: float) -> bool:
        """True when `value` fails the gate."""
        return OPS[self.op](value, self.threshold)


def parse(text: str, known: Mapping[str, str], option: str = "--fail-on") -> tuple[Condition, ...]:
    """The conditions of an expression; `known` maps every metric name this command measures to its meaning."""
    parts = text.split(",")
    if not text.strip() or any(not p.strip() for p in parts):
        msg = f"{option} {text!r}: empty condition; write METRIC OP NUMBER, comma-separated, e.g. heading_error_deg>5"
        raise GateSyntaxError(msg)
    out = []
    for part in parts:
        m = _CONDITION.match(part)
        if m is None:
            msg = (f"{option}: {part.strip()!r} is not METRIC OP NUMBER (OP one of >, >=, <, <=), "
                   "e.g. heading_error_deg>5")
            raise GateSyntaxError(msg)
        metric, op, number = m.groups()
        if metric not in known:
            msg = f"{option}: unknown metric {metric!r}; this command measures {', '.join(sorted(known))}"
            raise GateSyntaxError(msg)
        out.append(Condition(metric, op, float(number)))
    return tuple(out)


def failures(conditions: tuple[Condition, ...], metrics: Mapping[str, float | None],
             why_missing: Mapping[str, str] | None = None) -> list[str]:
    """The conditions that fail for one magnetometer, each with the measured value (or why it is missing)."""
    out = []
    for c in conditions:
        value = metrics.get(c.metric)
        if value is None:
            reason = (why_missing or {}).get(c.metric, "not measured")
            out.append(f"{c} (not measured: {reason})")
        elif c.holds(value):
            out.append(f"{c} (measured {value:.3g})")
    return out
