"""docs/: the CLI reference is the current `--help`, and links point at files that exist."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _generator() -> ModuleType:
    """docs/cli_reference.py, imported from its path (docs/ is not a package)."""
    spec = importlib.util.spec_from_file_location("cli_reference", DOCS / "cli_reference.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_reference_is_current() -> None:
    """docs/cli-reference.md is what the generator writes from today's --help."""
    assert (DOCS / "cli-reference.md").read_text() == _generator().render(), (
        "docs/cli-reference.md is out of date with the commands' --help; regenerate it with "
        "`python docs/cli_reference.py` and commit the result")


def test_docs_link_to_files_that_exist() -> None:
    """Relative links and images in docs/ point at files in the repository."""
    for page in DOCS.rglob("*.md"):
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", page.read_text()):
            assert (page.parent / target).exists(), f"{page.relative_to(ROOT)} links to {target}, which is missing"
