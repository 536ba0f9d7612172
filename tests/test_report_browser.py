"""report.html in headless Chromium: it loads without console errors and every image decodes (issue 13 item 1).

The test also writes the screenshots the documentation shows (docs/images/). It skips, saying why, where
Debian's `chromium` is not installed (apt-get install chromium) or the real logs are absent.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate
from magcal_cli.writers import write_outputs

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"

#: injected before the page's own content: records script errors and failed resources, then, once the page
#: has loaded, writes what it found into the DOM, where --dump-dom can read it
PROBE = """<script>
window.__errors = [];
window.addEventListener('error', e => window.__errors.push(String(e.message || (e.target && e.target.src) || 'error')), true);
const __consoleError = console.error;
console.error = (...a) => { window.__errors.push(a.join(' ')); __consoleError(...a); };
window.addEventListener('load', () => {
  const broken = [...document.images].filter(i => !i.complete || i.naturalWidth === 0).map(i => i.alt);
  const out = document.createElement('pre');
  out.id = 'magcal-probe';
  out.textContent = JSON.stringify({images: document.images.length, broken: broken, errors: window.__errors});
  document.body.appendChild(out);
});
</script>"""


def _chromium() -> str:
    """The Chromium binary, or a skip that says how to get it."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("the chromium binary is not installed (Debian: apt-get install -y chromium)")
    return exe


def _browse(exe: str, page: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run headless Chromium on a local page with the given extra arguments."""
    cmd = [exe, "--headless", "--disable-gpu", "--no-sandbox", "--hide-scrollbars", "--enable-logging=stderr",
           "--v=0", "--virtual-time-budget=5000", *args, page.as_uri()]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)


def check_in_browser(html: Path, screenshot: Path) -> dict[str, object]:
    """Load the report (with the probe) in Chromium, assert it is clean, and save a screenshot of the page top."""
    exe = _chromium()
    probed = html.with_name("probed.html")
    probed.write_text(html.read_text(encoding="utf-8").replace("<head>", "<head>" + PROBE, 1), encoding="utf-8")
    run = _browse(exe, probed, "--dump-dom")
    found = re.search(r"<pre id=\"magcal-probe\">(.*?)</pre>", run.stdout, re.DOTALL)
    assert found, f"the page did not finish loading in Chromium:\n{run.stderr[-2000:]}"
    probe = json.loads(found.group(1).replace("&quot;", '"').replace("&amp;", "&"))
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line]
    assert probe["errors"] == [] and console == [], (probe["errors"], console)
    assert probe["broken"] == [], f"images that did not decode: {probe['broken']}"
    screenshot.parent.mkdir(parents=True, exist_ok=True)
    shot = _browse(exe, html, f"--screenshot={screenshot}", "--window-size=1280,2400")
    assert screenshot.is_file() and screenshot.stat().st_size > 10_000, shot.stderr[-2000:]
    return probe


def _report(log: Path, out: Path, cfg: Config) -> Path:
    """Fit `log` and write its HTML report into `out`."""
    result = calibrate(log, cfg)
    (html,) = write_outputs(result, out, ["plots"])
    return html


def _offline(html: Path) -> None:
    """The page names no external resource: every image is embedded, there is no script or stylesheet link."""
    text = html.read_text(encoding="utf-8")
    assert not re.search(r"(src|href)=['\"](https?:|//)", text)
    assert "<script" not in text and "<link" not in text
    assert all(src.startswith("data:image/svg+xml;base64,") for src in re.findall(r"<img src='([^']*)'", text))


def test_sample_log_report_in_chromium(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The sample hand-held log: clean load, every plot present (3 per magnetometer), screenshot for the docs."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1767225600")          # a fixed date in the screenshot
    html = _report(ROOT / "sample_logs" / "handheld.mcap", tmp_path, Config(diagnose=True))
    _offline(html)
    probe = check_in_browser(html, IMAGES / "report-handheld.png")
    assert probe["images"] == 3


@pytest.mark.slow
def test_log171_report_in_chromium(realdata: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """log171 (ArduPilot, three compasses, default effects: about a minute): clean load, screenshot for the docs."""
    log = realdata / "ardupilot" / "log171.bin"
    if not log.is_file():
        pytest.skip(f"{log} is absent (see ../shared/realdata/README.md)")
    _chromium()
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1767225600")
    html = _report(log, tmp_path, Config(diagnose=True))
    _offline(html)
    probe = check_in_browser(html, IMAGES / "report-log171.png")
    # 4 per compass (sphere, over time, quality, modelled effects) and the heading check's figure (issue 38)
    assert probe["images"] == 13
    assert "Warnings and notes" in html.read_text(encoding="utf-8")
