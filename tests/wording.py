"""Helpers for tests that read messages as a person would (tests/cli/test_messages.py, tests/diagnose/test_summary.py)."""

from __future__ import annotations


def depth(text: str) -> int:
    """How deep the round brackets of `text` nest."""
    level = deepest = 0
    for c in text:
        level += (c == "(") - (c == ")")
        deepest = max(deepest, level)
    return deepest
