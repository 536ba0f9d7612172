"""Findings: what a run noticed, as data (the CLI decides what to print or fail on)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class Severity(Enum):
    """How much a finding matters to the user."""

    INFO = "info"
    WARNING = "warning"


@dataclass(frozen=True)
class Finding:
    """One remark: a stable `code` for scripts, a one-sentence `message` for people, numbers as `evidence`."""

    severity: Severity
    code: str
    message: str
    evidence: dict[str, Any] = field(default_factory=dict)
