"""Golden-file comparison shared by the writer tests (`pytest --update-golden` rewrites the files)."""

from __future__ import annotations

from pathlib import Path

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


def check_golden(name: str, text: str, update: bool) -> None:
    """Compare `text` with tests/golden/<name>, or rewrite the file when --update-golden is given."""
    path = GOLDEN / name
    if update:
        path.write_text(text, encoding="utf-8")
    assert path.is_file(), f"{path} is missing; run pytest --update-golden"
    assert text == path.read_text(encoding="utf-8"), f"{name} differs from the golden file"
