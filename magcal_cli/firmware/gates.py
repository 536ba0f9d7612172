"""Quality gates: the small expression language of `fit --fail-on` and `check --fail-on`.

    EXPR      := CONDITION ("," CONDITION)*
    CONDITION := METRIC OP NUMBER          e.g. heading_error_deg>5
    OP        := ">" | ">=" | "<" | "<="
    NUMBER    := a decimal number, optionally with an exponent (2, 0.5, 1e-3)

Each condition describes a failure. `judge` sorts the conditions that hold from those whose metric could not
be measured: `magcal check` reports the latter as "not measured" (failing only with --require-measured), while
`fit --fail-on` (`failures`) counts both, since what the fit cannot measure cannot pass its gate. The expression
is parsed with one regular expression per condition; nothing is evaluated as code.
"""

from __future__ import annotations

import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from magcal_cli.errors import MagcalError

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


def _verdict(c: Condition, metrics: Mapping[str, float | None], why_missing: Mapping[str, str] | None
             ) -> tuple[str, bool] | None:
    """(text, measured) when `c` fails or cannot be measured; None when it passes."""
    value = metrics.get(c.metric)
    if value is None:
        return f"{c} (not measured: {(why_missing or {}).get(c.metric, 'not measured')})", False
    return (f"{c} (measured {value:.3g})", True) if c.holds(value) else None


def judge(conditions: tuple[Condition, ...], metrics: Mapping[str, float | None],
          why_missing: Mapping[str, str] | None = None) -> tuple[list[str], list[str]]:
    """(conditions that hold, with the measured value; conditions whose metric is missing, with why)."""
    verdicts = [v for v in (_verdict(c, metrics, why_missing) for c in conditions) if v is not None]
    return [t for t, measured in verdicts if measured], [t for t, measured in verdicts if not measured]


def failures(conditions: tuple[Condition, ...], metrics: Mapping[str, float | None],
             why_missing: Mapping[str, str] | None = None) -> list[str]:
    """The conditions that fail for one magnetometer, one whose metric could not be measured included."""
    return [v[0] for v in (_verdict(c, metrics, why_missing) for c in conditions) if v is not None]
