"""The README's set-up commands are the ones CI runs, and they name files that exist."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup_commands() -> list[str]:
    """The shell lines of the first code block of the README."""
    block = re.search(r"```sh\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert block, "README.md has no ```sh block"
    return [ln for ln in block.group(1).splitlines() if ln.strip() and not ln.startswith("#")]


def test_exactly_two_setup_commands_that_ci_runs() -> None:
    """One installs and fits a shipped sample log, one installs and runs the tests; .ci/run uses the latter."""
    cmds = _setup_commands()
    assert len(cmds) == 2
    fit_cmd, test_cmd = cmds
    log = re.search(r"magcal fit (\S+)", fit_cmd)
    assert log and (ROOT / log.group(1)).is_file()
    assert "pytest" in test_cmd and "'.[test]'" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text()
    assert "pip install -e '.[test]'" in ci and "README.md" in ci
