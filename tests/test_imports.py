"""What importing the package and reading a log import: no heavy module a run does not need (issue 27).

scipy.stats costs 0.3-1.2 s to import, matplotlib 0.3 s, scipy.spatial 0.2 s, scipy.interpolate and scipy.optimize
0.1 s each (beyond the scipy.linalg every fit needs); the format libraries are each
imported by their own reader only. Each case runs in a fresh interpreter, so the modules it finds are the ones
that code path imported.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_logs"
#: imported only by the code that needs them
HEAVY = ("scipy.stats", "scipy.spatial", "scipy.signal", "scipy.interpolate", "scipy.optimize", "matplotlib", "mcap",
         "rosbags", "pymavlink", "pyulog")
FORMATS = ("mcap", "rosbags", "pymavlink", "pyulog")


def _imported(code: str) -> set[str]:
    """The modules of HEAVY (and numpy) in sys.modules after running `code` in a fresh interpreter."""
    probe = (f"{code}\nimport json, sys\n"
             f"print(json.dumps([m for m in {(*HEAVY, 'numpy')!r} if m in sys.modules]))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True,
                         timeout=120)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_cli_imports_no_numpy() -> None:
    """`magcal --help` and every command's --help need neither numpy nor anything heavier."""
    assert _imported("import magcal_cli.cli.main") == set()


def test_pipeline_imports_nothing_heavy() -> None:
    """Importing the pipeline (what `fit` does first) brings none of the heavy modules."""
    assert _imported("import magcal_cli.pipeline") & set(HEAVY) == set()


@pytest.mark.parametrize(("log", "own"), [("handheld.bin", set()), ("handheld.mcap", {"mcap", "rosbags"}),
                                          ("handheld.ulg", {"pyulog"}), ("handheld.bag", {"rosbags"})])
def test_reader_imports_only_its_format_library(log: str, own: set[str]) -> None:
    """Reading a log imports its own format library and no other one (and neither scipy.stats nor matplotlib)."""
    found = _imported(f"from magcal_cli.readers import open_recording\nopen_recording({str(SAMPLES / log)!r})")
    assert found & {*FORMATS, "scipy.stats", "matplotlib"} <= own


def test_a_default_fit_imports_nothing_heavy(tmp_path: Path) -> None:
    """A default fit (diagnosis on) of the sample log, and a flight log's GPS acceleration, need none of scipy.stats,
    scipy.signal, scipy.spatial, scipy.interpolate, scipy.optimize or matplotlib (0.1-1.2 s each): the p-values come
    from scipy.special; the Gumbel tail, the Savitzky-Golay derivative, the rotations and the spline are computed
    as scipy would (ppc.gumbel_fit and brentq, nongravity, so3, spline), and the report draws its own SVG."""
    found = _imported("from magcal_cli.cli.main import cli\n"
                      f"cli(['fit', {str(SAMPLES / 'handheld.bin')!r}, '-o', {str(tmp_path)!r}, '-q'], "
                      "standalone_mode=False)\n"
                      "import numpy as np\n"
                      "from magcal_cli.streams import Kind, Stream\n"
                      "from magcal_cli.effects.nongravity import acceleration_grid\n"
                      "t = np.arange(0, 60, 0.2)\n"
                      "pos = np.stack([47 + 1e-5 * np.sin(t / 5), 8 + 1e-5 * np.cos(t / 5), 400 + 0 * t], axis=1)\n"
                      "acceleration_grid(Stream(Kind.POSITION, 'gps', t, pos, 'test', 'deg'))")
    assert found & set(HEAVY) == set()
    assert (tmp_path / "calibration.json").is_file()
