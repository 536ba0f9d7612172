"""What `magcal fit` costs end to end, stage by stage, and against its solver (issue 27).

For each of four logs (the shipped sample, a simulated 5-minute hand-held MCAP with a 100 Hz IMU and a 50 Hz
magnetometer, ArduPilot log171 and BROAD trial 06; a log whose file is absent is skipped, saying so):

- the whole process `magcal fit LOG -o TMP --force -q`, default and `--effects none`: wall time (median of
  `--repeats`) and the child's peak memory (ru_maxrss from wait4: its largest process; and the peak of the summed
  PSS of it and the diagnosis workers it forks, sampled every 25 ms in one more run of each, which is not timed:
  the sampling slowed log171 by 0.4-0.5 s);
- per stage, in one fresh interpreter per package: import (everything a default `fit` of this log imports,
  found by running it once), read (`readers.open_recording`), detect/select (`pipeline.select_streams`: still
  segments, impacts, timing), fit (the method with `--effects none`), the rest of `calibrate_recording` (the
  choice of method, document, quality, findings), diagnose (the method's time with the default `--effects auto`
  minus its time with none), write (json, yaml, report.txt and the firmware file `fit` adds), plots
  (report.html);
- the solver's time: the wall time during which a Levenberg-Marquardt loop runs (`models.solve.solve` and
  `models.solve.iterate`, wrapped before anything imports them; overlapping calls on the diagnosis' threads
  and forked workers count once), in the `--effects none` fit and in the default one, and the ratio whole process / solver;
- `magcal fit --help`'s wall time;
- whether the default run's calibration.json is the same (created_utc aside) before and after.

`--before DIR` runs an older checkout (its folder holding `magcal_cli/`, e.g. /tmp/before27) in the same run,
interleaved with this tree (the order alternates between repeats), and prints both side by side with the ratio
after / before. Each package runs with PYTHONPATH set to its folder and the working directory outside both trees,
its bytecode compiled beforehand as an installed package's is (PYTHONDONTWRITEBYTECODE is dropped for the runs).
Timings on a shared machine are noisy: compare before and after from the same run only.

    python benchmarks/bench_end_to_end.py [--before /tmp/before27] [--repeats 3] [--stage-repeats N]
                                          [--logs sample,sim5min,log171,broad06] [--out docs/results/speed.md]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, redirect_stdout, suppress
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from same_outputs import shifts  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
HERE = Path(__file__).resolve()
TIMEOUT = 1800.0
#: the simulated log: `magcal simulate` options
SIM_ARGS = ("--scenario", "handheld", "--duration", "300", "--rate", "100", "--mag-rate", "50", "--seed", "1")
#: what one stage run reports, in table order (key, label)
STAGES = (("import", "import"), ("read", "read"), ("select", "detect/select"), ("fit", "fit (method, effects none)"),
          ("assemble", "rest of calibrate_recording (choose, assemble)"), ("diagnose", "diagnose (method default - none)"),
          ("write", "write (json, yaml, txt, firmware)"), ("plots", "plots (report.html)"))


# ---------------------------------------------------------------------------------------------------------------
# inside the child interpreter (--driver): the package under test is the one on PYTHONPATH


class SolverClock:
    """Wall time during which any solver call runs: outermost calls per thread, overlapping intervals merged. The
    diagnosis' forked workers (diagnose/forked.py) inherit the clock: each process appends its intervals to one
    file (CLOCK_MONOTONIC, so they compare across processes), and `seconds` merges them all."""

    def __init__(self) -> None:
        self.local = threading.local()
        self.path = Path(tempfile.mkstemp(prefix="magcal-solver-")[1])

    @property
    def spans(self) -> list[tuple[float, float]]:
        """Every process's intervals."""
        return [(float(a), float(b)) for a, b in (line.split() for line in self.path.read_text().splitlines())]

    @property
    def calls(self) -> int:
        """Outermost solver calls, in every process."""
        return len(self.spans)

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """`fn`, timed when it is the outermost solver call of its thread."""
        def timed(*args: Any, **kwargs: Any) -> Any:
            depth = getattr(self.local, "depth", 0)
            self.local.depth = depth + 1
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.local.depth = depth
                if depth == 0:
                    fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
                    os.write(fd, f"{t0!r} {time.perf_counter()!r}\n".encode())      # one atomic append
                    os.close(fd)

        timed.__wrapped__ = fn  # type: ignore[attr-defined]
        return timed

    def reset(self) -> None:
        """Forget the calls so far."""
        self.path.write_text("")

    def seconds(self) -> float:
        """The union of the recorded intervals."""
        total, end = 0.0, -float("inf")
        for a, b in sorted(self.spans):
            if b <= end:
                continue
            total += b - max(a, end)
            end = b
        return total


def _driver_modules(log: Path, out: Path) -> None:
    """Run a default `magcal fit LOG` in this interpreter and print the modules it imported, in order."""
    before = set(sys.modules)
    from magcal_cli.cli.main import main

    sys.argv = ["magcal", "fit", str(log), "-o", str(out), "--force", "-q"]
    with suppress(SystemExit), Path(os.devnull).open("w") as quiet, redirect_stdout(quiet):
        main()
    names = [n for n in sys.modules if n not in before and n != "__main__" and not n.startswith("magcal_cli.__main__")]
    print(json.dumps(names))


@contextmanager
def _timed(into: dict[str, float], key: str) -> Iterator[None]:
    t0 = time.perf_counter()
    try:
        yield
    finally:
        into[key] = into.get(key, 0.0) + time.perf_counter() - t0


def _driver_stages(log: Path, out: Path, modules: Sequence[str]) -> None:
    """Time the stages of a fit of `log` through the public API and print them as JSON."""
    stages: dict[str, float] = {}
    clock = SolverClock()
    t0 = time.perf_counter()
    solve_mod = importlib.import_module("magcal_cli.models.solve")
    # wrapped before anything binds them with `from magcal_cli.models.solve import solve`
    for name in ("solve", "iterate"):
        if hasattr(solve_mod, name):
            setattr(solve_mod, name, clock.wrap(getattr(solve_mod, name)))
    for name in modules:
        try:
            importlib.import_module(name)
        except Exception:  # a module that imports only in its parent's context
            continue
    stages["import"] = time.perf_counter() - t0

    from magcal_cli import pipeline
    from magcal_cli.config import Config
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.writers import FIRMWARE_OUTPUTS, write_outputs

    inner: dict[str, float] = {}
    for name, key in (("select_streams", "select"), ("run_method", "method")):
        fn = getattr(pipeline, name, None)
        if fn is not None:
            def timed(*args: Any, _fn: Callable[..., Any] = fn, _key: str = key, **kwargs: Any) -> Any:
                with _timed(inner, _key):
                    return _fn(*args, **kwargs)

            setattr(pipeline, name, timed)

    def config(auto: bool) -> Any:
        make = getattr(pipeline, "command_config", None)
        if make is not None:
            return make(effects=None if auto else ())
        return Config(allow_truncated=True, diagnose=auto)

    with _timed(stages, "read"):
        rec = open_recording(log, None, ReadOptions(allow_truncated=True))
    runs: dict[str, dict[str, float]] = {}
    results = {}
    for label, auto in (("none", False), ("default", True)):
        inner.clear()
        clock.reset()
        t = time.perf_counter()
        results[label] = pipeline.calibrate_recording(rec, config(auto))
        total = time.perf_counter() - t
        runs[label] = {"total": total, "select": inner.get("select", float("nan")),
                       "method": inner.get("method", float("nan")), "solver": clock.seconds(),
                       "solver_calls": clock.calls}
    none, default = runs["none"], runs["default"]
    stages["select"] = none["select"]
    stages["fit"] = none["method"]
    stages["assemble"] = none["total"] - none["select"] - none["method"]
    stages["diagnose"] = default["method"] - none["method"]
    result = results["default"]
    names = ["json", "yaml", "report"]
    firmware = FIRMWARE_OUTPUTS.get(result.recording.format)
    with _timed(stages, "write"):
        try:
            write_outputs(result, out, [*names, firmware] if firmware else names)
        except Exception:  # fit skips a firmware file the calibration cannot be written as
            write_outputs(result, out, names)
    with _timed(stages, "plots"):
        write_outputs(result, out, ["html"])
    import magcal_cli

    print(json.dumps({"stages": stages, "runs": runs, "package": str(Path(magcal_cli.__file__).parent.parent)}))


# ---------------------------------------------------------------------------------------------------------------
# the parent: runs the children, interleaved, and makes the table


def _env(package: Path) -> dict[str, str]:
    """The child's environment: `package` first on the path, and bytecode cached as an installed package has it
    (pip compiles it at install; a PYTHONDONTWRITEBYTECODE=1 shell would make every run compile ~200 modules,
    0.1 s of a 1 s fit)."""
    env = dict(os.environ, PYTHONPATH=str(package.resolve()))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _compiled(package: Path) -> None:
    """Compile the package's modules once, before anything is timed."""
    import compileall

    compileall.compile_dir(str(package / "magcal_cli"), quiet=1)


def tree_pss_mb(pid: int) -> float:
    """The summed proportional set size (MB) of process `pid` and its descendants now: the memory they take
    between them, pages a forked worker shares with its parent counted once (Linux; 0 elsewhere)."""
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            todo.extend(int(c) for c in Path(f"/proc/{p}/task/{p}/children").read_text().split())
            rollup = Path(f"/proc/{p}/smaps_rollup").read_text().splitlines()
            total += next((int(line.split()[1]) for line in rollup if line.startswith("Pss:")), 0) / 1024.0
        except (OSError, ValueError):
            continue
    return total


def run_timed(cmd: list[str], package: Path, cwd: Path, timeout: float = TIMEOUT, pss: bool = False
              ) -> dict[str, Any]:
    """Run `cmd` with `package` first on the path: wall seconds, peak resident memory (MB), exit code, stderr tail;
    with `pss`, also the peak summed PSS of its process tree, sampled every 25 ms. Reading smaps_rollup walks
    the page tables under each process's mmap lock: on log171 it slowed the run it sampled by 0.4-0.5 s (6.3-6.7 s
    against 5.7-6.1 s unsampled, 2 cores), so a timed run does not sample it (`measure` runs one more for it)."""
    with tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=_env(package), cwd=cwd, stdout=subprocess.DEVNULL, stderr=err)
        deadline = t0 + timeout
        peak_pss, polls = 0.0, 0
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            polls += 1
            if pss and polls % 5 == 0:                  # every 25 ms
                peak_pss = max(peak_pss, tree_pss_mb(proc.pid))
            if time.perf_counter() > deadline:
                proc.kill()
                pid, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.005)
        seconds = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        tail = err.read().decode(errors="replace").strip().splitlines()[-1:]
    return {"seconds": seconds, "peak_mb": usage.ru_maxrss / 1024.0, "pss_mb": peak_pss if pss else float("nan"),
            "exit": proc.returncode,
            "error": tail[0] if tail and proc.returncode else None}


def run_json(cmd: list[str], package: Path, cwd: Path) -> Any:
    """Run a driver child and parse the last line it prints."""
    proc = subprocess.run(cmd, env=_env(package), cwd=cwd, capture_output=True, text=True, timeout=TIMEOUT,
                          check=False)
    if proc.returncode != 0 or not proc.stdout.strip():
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        msg = f"{' '.join(cmd[2:5])}: exit {proc.returncode}: {tail}"
        raise RuntimeError(msg)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def numbers(doc: Any) -> Iterator[tuple[str, Any]]:
    """(path, leaf) of a JSON document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from ((f"{k}.{p}" if p else k, x) for p, x in numbers(v))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from ((f"{i}.{p}" if p else str(i), x) for p, x in numbers(v))
    else:
        yield "", doc


def same_result(a: Path, b: Path) -> str:
    """'same' when two calibration.json files agree (created_utc aside), else what differs."""
    if not a.exists() or not b.exists():
        return "—"
    da, db = json.loads(a.read_text()), json.loads(b.read_text())
    for d in (da, db):
        d.pop("created_utc", None)
    if da == db:
        return "same"
    la, lb = dict(numbers(da)), dict(numbers(db))
    keys = set(la) ^ set(lb)
    worst, where = 0.0, ""
    for k in set(la) & set(lb):
        x, y = la[k], lb[k]
        if x == y:
            continue
        if isinstance(x, float | int) and isinstance(y, float | int) and not isinstance(x, bool):
            rel = abs(x - y) / max(abs(x), abs(y), 1e-300)
            if rel > worst:
                worst, where = rel, k
        else:
            keys.add(k)
    parts = ([f"max rel diff {worst:.1e} ({where})"] if worst else []) + ([f"{len(keys)} fields differ "
                                                                            f"({sorted(keys)[0]}...)"] if keys else [])
    cal, eff, verdicts = shifts(a, b)
    return "differs: " + "; ".join(parts) + (f"; D/o/dip moved <= {cal:.3f} std, effect parameters <= {eff:.3f} "
                                             f"std, verdicts {'the same' if verdicts else 'DIFFERENT'}")


def median(xs: Sequence[float]) -> float:
    """Median, NaN for none."""
    xs = [x for x in xs if x == x]
    return statistics.median(xs) if xs else float("nan")


class Side:
    """One package under test and what was measured with it."""

    def __init__(self, name: str, package: Path) -> None:
        self.name, self.package = name, package
        self.modules: dict[str, list[str]] = {}
        self.whole: dict[tuple[str, str], list[dict[str, Any]]] = {}
        self.memory: dict[tuple[str, str], list[dict[str, Any]]] = {}
        self.stages: dict[str, list[dict[str, Any]]] = {}
        self.help: list[float] = []
        self.errors: dict[str, str] = {}


def fit_cmd(log: Path, out: Path, *extra: str) -> list[str]:
    """`magcal fit LOG -o OUT --force -q EXTRA`."""
    return [sys.executable, "-m", "magcal_cli", "fit", str(log), "-o", str(out), "--force", "-q", *extra]


def measure(name: str, log: Path, sides: list[Side], repeats: int, stage_repeats: int, work: Path) -> None:
    """Whole-process and stage runs of one log, interleaved between the sides."""
    for r in range(repeats):
        for side in sides if r % 2 == 0 else sides[::-1]:
            for mode, extra in (("default", ()), ("none", ("--effects", "none"))):
                out = work / f"{side.name}-{name}-{mode}"
                res = run_timed(fit_cmd(log, out, *extra), side.package, work)
                side.whole.setdefault((name, mode), []).append(res)
                print(f"  {side.name:6} {mode:7} {res['seconds']:7.2f} s {res['peak_mb']:6.0f} MB"
                      + (f"  exit {res['exit']}: {res['error']}" if res["exit"] else ""), flush=True)
    for side in sides:                  # the processes' PSS in runs of their own: sampling it slows what it samples
        for mode, extra in (("default", ()), ("none", ("--effects", "none"))):
            res = run_timed(fit_cmd(log, work / f"{side.name}-{name}-{mode}", *extra), side.package, work, pss=True)
            side.memory.setdefault((name, mode), []).append(res)
            print(f"  {side.name:6} {mode:7} processes' PSS {res['pss_mb']:4.0f} MB (untimed)", flush=True)
    for side in sides:
        out = work / f"{side.name}-{name}-modules"
        try:
            side.modules[name] = run_json([sys.executable, str(HERE), "--driver", "modules", str(log), str(out)],
                                          side.package, work)
        except RuntimeError as exc:
            side.errors[name] = str(exc)
    for r in range(stage_repeats):
        for side in sides if r % 2 == 0 else sides[::-1]:
            if name not in side.modules:
                continue
            mods = work / f"{side.name}-{name}-modules.json"
            mods.write_text(json.dumps(side.modules[name]))
            out = work / f"{side.name}-{name}-stages"
            try:
                st = run_json([sys.executable, str(HERE), "--driver", "stages", str(log), str(out), str(mods)],
                              side.package, work)
            except RuntimeError as exc:
                side.errors[name] = str(exc)
                continue
            if Path(st["package"]).resolve() != side.package.resolve():
                side.errors[name] = f"ran the package in {st['package']}, not {side.package}"
            side.stages.setdefault(name, []).append(st)
            print(f"  {side.name:6} stages " + ", ".join(f"{k} {v:.2f}" for k, v in st["stages"].items())
                  + f", solver none {st['runs']['none']['solver']:.2f} default {st['runs']['default']['solver']:.2f}",
                  flush=True)


def rows_for(name: str, side: Side) -> dict[str, float]:
    """The medians of one log and side, by row label."""
    out: dict[str, float] = {}
    whole = {mode: side.whole.get((name, mode), []) for mode in ("default", "none")}
    for mode, runs in whole.items():
        ok = [r for r in runs if r["exit"] == 0]
        out[f"whole process, {mode} (s)"] = median([r["seconds"] for r in ok])
        out[f"peak memory, {mode} (MB)"] = median([r["peak_mb"] for r in ok])
        out[f"peak memory of all processes (PSS), {mode} (MB)"] = median(
            [r["pss_mb"] for r in side.memory.get((name, mode), []) if r["exit"] == 0])
    stages = side.stages.get(name, [])
    for key, label in STAGES:
        out[f"{label} (s)"] = median([s["stages"][key] for s in stages])
    accounted = sum(out[f"{label} (s)"] for _, label in STAGES)
    out["whole default - sum of stages (s)"] = out["whole process, default (s)"] - accounted
    for mode in ("none", "default"):
        solver = median([s["runs"][mode]["solver"] for s in stages])
        out[f"solver, {mode} (s)"] = solver
        out[f"solver calls, {mode}"] = median([s["runs"][mode]["solver_calls"] for s in stages])
        out[f"whole / solver, {mode}"] = out[f"whole process, {mode} (s)"] / solver if solver > 0 else float("nan")
    return out


def fmt(x: float, label: str) -> str:
    """A table cell."""
    if x != x:
        return "—"
    if "calls" in label:
        return f"{x:.0f}"
    if "MB" in label:
        return f"{x:.0f}"
    if "/" in label and "(s)" not in label:
        return f"{x:.1f}×"
    return f"{x:.2f}"


def table(logs: list[tuple[str, Path | None, str]], sides: list[Side], results: dict[str, str]) -> str:
    """The markdown table: one block of rows per log, one column per side and the ratio after / before."""
    before = len(sides) > 1
    head = "| log | what | " + ("before | after | after/before |" if before else "after |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for name, log, title in logs:
        if log is None:
            lines.append(f"| {title} | skipped: file absent | " + ("| | |" if before else "|"))
            continue
        cols = [rows_for(name, s) for s in sides]
        for i, label in enumerate(cols[0]):
            cells = [fmt(c[label], label) for c in cols]
            if before:
                a, b = cols[1][label], cols[0][label]
                ratio = f"{a / b:.2f}" if b == b and a == a and b != 0 and "calls" not in label and "sum of" not in label else ""
                cells.append(ratio)
            lines.append(f"| {title if i == 0 else ''} | {label} | " + " | ".join(cells) + " |")
        if before:
            lines.append(f"| | default calibration.json before vs after | {results.get(name, '—')} | | |")
        for s in sides:
            runs = [r for mode in ("default", "none") for r in s.whole.get((name, mode), [])]
            bad = [r for r in runs if r["exit"] != 0]
            if bad:
                lines.append(f"| | {s.name}: {len(bad)} of {len(runs)} whole runs failed (left out) | "
                             f"{(bad[0]['error'] or '')[:200]} |" + (" | |" if before else ""))
            if name in s.errors:
                lines.append(f"| | {s.name}: stage run failed | {s.errors[name][:200]} |" + (" | |" if before else ""))
    helps = [median(s.help) for s in sides]
    cells = [f"{h:.2f}" for h in helps] + ([f"{helps[1] / helps[0]:.2f}"] if before else [])
    lines.append("| (any) | `magcal fit --help` (s) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    """Measure every log on every side, print the table and write it with --out."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, default=None, help="an older checkout (folder holding magcal_cli/)")
    ap.add_argument("--repeats", type=int, default=3, help="whole-process runs per log and side (median)")
    ap.add_argument("--stage-repeats", type=int, default=None,
                    help="stage runs per log and side (median) [default: --repeats]")
    ap.add_argument("--logs", default="sample,sim5min,log171,broad06", help="which logs, comma-separated")
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--sim", type=Path, default=None, help="an existing simulated 5-min log to use")
    ap.add_argument("--out", type=Path, default=None, help="write the markdown table here (docs/results/speed.md)")
    ap.add_argument("--driver", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.stage_repeats = args.repeats if args.stage_repeats is None else args.stage_repeats
    if args.driver:
        what, log, out, *rest = args.driver
        if what == "modules":
            _driver_modules(Path(log), Path(out))
        else:
            _driver_stages(Path(log), Path(out), json.loads(Path(rest[0]).read_text()))
        return
    sides = ([Side("before", args.before)] if args.before else []) + [Side("after", ROOT)]
    for side in sides:
        _compiled(side.package)
    wanted = args.logs.split(",")
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="magcal-e2e-") as tmp:
        work = Path(tmp)
        sim = args.sim
        if "sim5min" in wanted and sim is None:
            sim = work / "handheld300.mcap"
            print(f"simulating {sim.name} ...", flush=True)
            subprocess.run([sys.executable, "-m", "magcal_cli", "simulate", "-o", str(sim), *SIM_ARGS, "-q"],
                           env=_env(sides[0].package), cwd=work, check=True, capture_output=True)
        known = {
            "sample": (ROOT / "sample_logs" / "handheld.bin", "sample_logs/handheld.bin"),
            "sim5min": (sim, "simulated 5-min hand-held MCAP (100/50 Hz)"),
            "log171": (args.realdata / "ardupilot" / "log171.bin", "ardupilot/log171.bin"),
            "broad06": (args.realdata / "broad" / "06_undisturbed_fast_rotation_A.mat", "broad/06 (fast rotation A)"),
        }
        unknown = [n for n in wanted if n not in known]
        if unknown:
            ap.error(f"--logs: unknown {', '.join(unknown)}; choose from {', '.join(known)}")
        logs: list[tuple[str, Path | None, str]] = []
        for name in wanted:
            path, title = known[name]
            if path is None or not path.exists():
                print(f"{name}: {path} is absent; skipped", flush=True)
                logs.append((name, None, title))
                continue
            logs.append((name, path.resolve(), title))
        for i in range(max(5, args.repeats)):
            for side in sides if i % 2 == 0 else sides[::-1]:
                side.help.append(run_timed([sys.executable, "-m", "magcal_cli", "fit", "--help"], side.package,
                                           work)["seconds"])
        results: dict[str, str] = {}
        for name, log, title in logs:
            if log is None:
                continue
            print(f"{title} ...", flush=True)
            measure(name, log, sides, args.repeats, args.stage_repeats, work)
            if len(sides) > 1:
                results[name] = same_result(work / f"before-{name}-default" / "calibration.json",
                                            work / f"after-{name}-default" / "calibration.json")
    load1 = os.getloadavg()
    text = table(logs, sides, results)
    print(text)
    if args.out is not None:
        cmd = "python benchmarks/bench_end_to_end.py" + (f" --before {args.before}" if args.before else "") + \
            f" --repeats {args.repeats}" + (f" --stage-repeats {args.stage_repeats}" if args.stage_repeats != args.repeats else "")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            "# What `magcal fit` costs, end to end and by stage (issue 27)\n\n"
            f"Made by `{cmd}` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
            f"load average {load0[0]:.1f} at the start and {load1[0]:.1f} at the end (this machine's speed drifts "
            "by 10-15 % from hour to hour: compare before and after within this table only). Whole process: `magcal fit LOG -o TMP --force -q`, "
            f"median of {args.repeats}, before and after interleaved; peak memory: the largest process's ru_maxrss "
            "(from wait4: the fit and the diagnosis workers it forked), and the peak of all its processes' summed "
            "proportional set size, sampled every 25 ms in one more run that is not timed (pages a worker shares with the "
            "fit counted once; reading them slowed log171's timed runs by 0.4-0.5 s). Stages: "
            f"one fresh interpreter per package and log (median of {args.stage_repeats}), through the public API "
            "(see the script's docstring); 'whole default - sum of stages' is interpreter start-up, the command line and "
            "what no stage covers, from different processes (noisy: negative when the diagnosis ran slower in the stage run). Solver: wall time inside `models.solve.solve`/`iterate` (overlapping calls on "
            "threads and in the diagnosis' forked workers counted once); whole / solver is the issue's end-to-end-to-solver ratio.\n\n" + text)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
