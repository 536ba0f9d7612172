"""The one loader behind every registry (readers, writers, log writers, methods): "module:attr" on use.

Registry values are import strings so that `magcal --help` does not import mcap, rosbags, pymavlink or
matplotlib; a value may also be the object itself (tests swap in fakes with `patch.dict`).
"""

from __future__ import annotations

import importlib
from typing import Any

from magcal_cli.errors import MissingDependencyError


def resolve(target: Any, purpose: str) -> Any:
    """The object named by "module:attr" (imported now), or `target` itself when it is not a string.

    `purpose` completes the sentence "<purpose> needs the package X" if an optional import is missing.
    """
    if not isinstance(target, str):
        return target
    module, attr = target.split(":")
    try:
        return getattr(importlib.import_module(module), attr)
    except ImportError as exc:
        msg = f"{purpose} needs the package {exc.name!r}; run: pip install --upgrade magcal-cli"
        raise MissingDependencyError(msg) from None
