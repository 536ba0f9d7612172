"""A fresh clone's transcript (docs/fresh-clone.md): the README's first command, then every command on a sample log
and on a real log, with the output a user sees, its exit code and wall time.

    python benchmarks/fresh_clone.py [--realdata ../shared/realdata] [--out docs/fresh-clone.md]

It clones this repository (its committed HEAD) into an empty folder, runs the README's install-and-fit command
there, and then each command from the clone's folder in the same virtual environment. stdout and stderr are shown
together in the order they appeared; long outputs are trimmed, saying where and how much.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KEEP_LINES = 24


def commands(real: Path) -> list[tuple[str, list[str]]]:
    """(section title, shell commands) in the order a new user would try them."""
    log171 = real / "ardupilot" / "log171.bin"
    ulg = real / "px4" / "sample.ulg"
    px4log = real / "px4" / "01_07_59.px4log"
    return [
        ("The group", ["magcal --version", "magcal --help"]),
        ("inspect", ["magcal inspect sample_logs/handheld.ulg", f"magcal inspect {log171}",
                     f"magcal inspect {log171} --json | head -c 300; echo"]),
        ("fit", ["magcal fit sample_logs/handheld.bin -o out/sample", f"magcal fit {log171} -o out/log171",
                 f"magcal fit {px4log} -o out/px4log"]),
        ("diagnose", ["magcal diagnose sample_logs/handheld.ulg", f"magcal diagnose {px4log}"]),
        ("check", [f"magcal check {log171} --no-refit", f"magcal check {px4log} --no-refit"]),
        ("export", ["magcal export out/log171/calibration.json --ardupilot out/log171.param",
                    "magcal export out/sample/calibration.json --px4 -"]),
        ("apply", ["magcal apply out/sample/calibration.json sample_logs/handheld.bin -o - | head -3"]),
        ("simulate", ["magcal simulate -o out/sim.ulg --scenario multirotor --seed 1 --duration 120",
                      "magcal simulate -o out/sim.bin --effects current_interference --seed 2"]),
        ("batch", [f"magcal batch sample_logs/handheld.ulg {ulg} -o out/batch --effects none"]),
        ("Mistakes", ["magcal fit sample_logs/handheld.bin -o README.md", "magcal fit sample_logs/handheld.bin "
                      "--mag 'MAG[5]' -o out/x", "magcal inspect --format mcap sample_logs/handheld.bin",
                      "magcal fit nonexistent.bin"]),
    ]


def run(cmd: str, cwd: Path, env_prefix: str) -> str:
    """One command through bash in `cwd`: its transcript block."""
    t0 = time.perf_counter()
    proc = subprocess.run(["bash", "-c", f"{env_prefix}{cmd}"], cwd=cwd, capture_output=False, check=False,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seconds = time.perf_counter() - t0
    lines = proc.stdout.rstrip("\n").splitlines()
    lines = [re.sub(r"\r.*\r", "", ln) for ln in lines]
    if len(lines) > KEEP_LINES:
        cut = len(lines) - KEEP_LINES
        lines = lines[:KEEP_LINES // 2] + [f"[... {cut} lines trimmed ...]"] + lines[-KEEP_LINES // 2:]
    body = "\n".join(lines)
    return f"$ {cmd}\n{body}\n[exit {proc.returncode}, {seconds:.1f} s]\n" if body else \
        f"$ {cmd}\n[exit {proc.returncode}, {seconds:.1f} s]\n"


def main(argv: list[str] | None = None) -> int:
    """Clone, install, run, write the transcript."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "fresh-clone.md")
    args = ap.parse_args(argv)
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "magcal"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        readme = (clone / "README.md").read_text()
        first = next(ln.strip() for ln in readme.splitlines() if "pip install -e . &&" in ln)
        blocks = ["## README command 1: install and calibrate the shipped sample log\n\n```\n"
                  + run(first.replace("pip install -e .", "pip install -q -e ."), clone, "") + "```\n"]
        env = f". {shlex.quote(str(clone / '.venv' / 'bin' / 'activate'))} && "
        (clone / "out").mkdir()
        for title, cmds in commands(args.realdata.resolve()):
            print(f"{title} ...", file=sys.stderr)
            blocks.append(f"## {title}\n\n```\n" + "\n".join(run(c, clone, env) for c in cmds) + "```\n")
    text = (f"# A fresh clone: the README's first command, then every command\n\n"
            f"Recorded on {time.strftime('%Y-%m-%d')} by `python benchmarks/fresh_clone.py`: it cloned the repository "
            f"at commit `{head}` into an empty folder on the project's machine (2 cores, Python "
            f"{sys.version.split()[0]}), ran the README's first command there (pip's own output quietened with "
            f"`-q`), then each command from the clone's folder in its virtual environment, on a shipped sample and "
            f"on real logs from `../shared/realdata/`. Each command is echoed after `$`, then its output (stdout and "
            f"stderr in the order they appeared; long outputs trimmed where marked), its exit code and wall time.\n\n"
            + "\n".join(blocks))
    args.out.write_text(text)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
