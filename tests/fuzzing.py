"""Fuzzing harness shared by tests/test_fuzz.py (a few hundred cases) and benchmarks/fuzz_campaign.py (thousands).

A second class of cases (issue 12) is a dead sensor: one magnetometer, accelerometer or gyroscope reading zero or
a constant throughout, in several formats; magcal must give the dead-sensor error, never exit 123.

Seeds are tiny simulated logs of every format; a mutation damages one copy (bit flips, byte insertions and
deletions, truncation, chunk duplication, zeroed runs, header damage) and `run_case` feeds it to `magcal inspect`
or `magcal fit` in-process through click's CliRunner, then checks the command-line contract: exit 0, 1 or 3;
on failure exactly one `Error:` line on stderr; on success a calibration document that loads; never a
traceback, never exit 123, never a partial or temporary file in the output directory.
"""

from __future__ import annotations

import dataclasses
import json
import random
import shutil
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from magcal_cli.synth.simulate import Simulation

#: the formats fuzzed; "log" is a text DataFlash log, "ros2" a ROS 2 bag directory with MCAP storage, "db3" one
#: with sqlite3 storage (its database read from the file's pages: sqlite_pages.py)
FORMATS = ("bin", "log", "ulg", "mcap", "bag", "ros2", "db3", "csv")
MUTATIONS = ("flip", "insert", "delete", "truncate", "duplicate", "zero", "header")
#: chunk size (bytes) of the MCAP and ROS 1 seeds: several chunks, so skipping one leaves the others
SEED_CHUNK = 16_000


@dataclass(frozen=True)
class Mutation:
    """One damage to a seed's bytes: what, where (fraction of the length), how many bytes, a random seed."""

    op: str
    where: float
    length: int
    seed: int

    def apply(self, data: bytes) -> bytes:
        """The damaged copy of `data`."""
        rng = random.Random(self.seed)
        n = len(data)
        b = bytearray(data)
        i = min(n - 1, int(self.where * n))
        k = max(1, self.length)
        if self.op == "flip":
            for _ in range(k):
                j = rng.randrange(n)
                b[j] ^= 1 << rng.randrange(8)
        elif self.op == "insert":
            b[i:i] = bytes(rng.randrange(256) for _ in range(k))
        elif self.op == "delete":
            del b[i:i + k]
        elif self.op == "truncate":
            del b[i:]
        elif self.op == "duplicate":
            j = rng.randrange(n)
            b[i:i] = data[j:j + k * 16]
        elif self.op == "zero":
            b[i:i + k * 16] = bytes(len(b[i:i + k * 16]))
        elif self.op == "header":
            for _ in range(k):
                b[rng.randrange(min(n, 512))] = rng.randrange(256)
        return bytes(b)


def random_mutation(rng: random.Random) -> Mutation:
    """A mutation drawn from `rng` (the campaign's generator; the test draws with hypothesis)."""
    return Mutation(rng.choice(MUTATIONS), rng.random(), rng.choice([1, 2, 4, 8, 37, 64, 300]), rng.randrange(1 << 30))


def text_log(raw_bin: Path, out: Path) -> None:
    """A text DataFlash log (`NAME, v1, v2, ...` lines, values scaled as Mission Planner prints them)."""
    from magcal_cli.readers.dataflash.binary import parse_binary

    raw = parse_binary(raw_bin)
    lines = [(-1, "FMT, 128, 89, FMT, BBnNZ, Type,Length,Name,Format,Columns")]
    for f in raw.formats.values():
        if f.name != "FMT":
            lines.append((-1, f"FMT, {f.type_id}, {f.length}, {f.name}, {f.format}, {','.join(f.columns)}"))
    for name, table in raw.tables.items():
        if name == "FMT":
            continue
        cols = []
        for c, ch in zip(table.fmt.columns, table.fmt.format, strict=False):
            cols.append(table.text(c) if ch in "nNZ" else [f"{v:.9g}" for v in table.num(c)])
        for k, pos in enumerate(table.pos.tolist()):
            lines.append((pos, ", ".join([name, *(col[k] for col in cols)])))
    lines.sort(key=lambda x: x[0])
    out.write_text("\n".join(line for _, line in lines) + "\n", encoding="latin-1")


def seed_simulation(path: Path) -> Simulation:
    """The simulation a seed at `path` is written from (handheld, 10 Hz IMU, 5 Hz field: about 80 s, fits in
    ~0.3 s): its IMU sampled as the format holds it (synth.logs.IMU_SAMPLING), its field read on IMU stamps (phase
    0: a CSV log has one row per IMU sample)."""
    from magcal_cli.synth.logs import imu_sampling
    from magcal_cli.synth.simulate import simulate

    return simulate("handheld", 0, rate=10.0, mag_rate=5.0, imu_sampling=imu_sampling(path), mag_phase_s=0.0)


def make_seeds(root: Path) -> dict[str, Path]:
    """One small simulated log per format (seed_simulation)."""
    from magcal_cli.synth.logs import write_log
    from magcal_cli.synth.logs.mcap import write_mcap
    from magcal_cli.synth.logs.rosbag import write_bag, write_ros2

    root.mkdir(parents=True, exist_ok=True)
    sim = seed_simulation(root / "seed.bin")                  # instantaneous IMU samples: every format but .ulg
    seeds = {}
    for fmt in ("bin", "ulg", "csv"):
        seeds[fmt] = root / f"seed.{fmt}"
        write_log(sim if fmt != "ulg" else seed_simulation(seeds[fmt]), seeds[fmt])
    seeds["mcap"] = root / "seed.mcap"
    write_mcap(sim, seeds["mcap"], chunk_size=SEED_CHUNK)
    seeds["bag"] = root / "seed.bag"
    write_bag(sim, seeds["bag"], chunk_size=SEED_CHUNK)
    seeds["ros2"] = root / "seed_ros2"
    write_log(sim, seeds["ros2"])
    seeds["db3"] = root / "seed_db3"
    write_ros2(sim, seeds["db3"], storage="sqlite3")
    seeds["log"] = root / "seed.log"
    text_log(seeds["bin"], seeds["log"])
    return seeds


#: the dead-sensor class (issue 12): one sensor reads zero, or one constant value, throughout the log
DEAD_KINDS = ("magnetometer", "accelerometer", "gyroscope")
DEAD_VALUES = ("zero", "constant")
DEAD_FORMATS = ("bin", "log", "ulg", "mcap", "bag", "csv")
#: the message every dead sensor must end with (detect.check_signal)
DEAD_MESSAGE = "the sensor is stuck, disconnected or not enabled"
#: bytes of an ArduPilot MAG record from MagX on (MagX..MOZ int16, Health uint8, S uint32) after its header,
#: TimeUS and I: the fields a dead compass logs as zero
MAG_FIELDS = (3 + 8 + 1, 9 * 2 + 1 + 4)


@dataclass(frozen=True)
class DeadSensor:
    """One sensor of a simulated log replaced by zeros or a constant (a dead, unplugged or disabled sensor)."""

    kind: str
    value: str

    def write(self, fmt: str, root: Path) -> Path:
        """A small simulated log of `fmt` with this sensor dead, written under `root`; the path to give magcal.

        A dead ArduPilot compass logs MAG records whose fields are all zero (Health too): the .bin is patched
        after writing, since the writer would apply the simulated onboard calibration to a zero field."""
        from magcal_cli.readers.dataflash.binary import parse_binary
        from magcal_cli.streams import Kind
        from magcal_cli.synth.logs import write_log

        path = root / f"dead.{fmt}"
        binary = root / "dead.bin"                                 # a text log is made from a binary one
        sim = seed_simulation(binary if fmt == "log" else path)
        kind = Kind(self.kind)
        patch = fmt in ("bin", "log") and kind is Kind.MAGNETOMETER and self.value == "zero"
        if not patch:
            streams = [dataclasses.replace(s, values=self._values(s.values)) if s.kind is kind else s
                       for s in sim.recording.streams]
            sim = dataclasses.replace(sim, recording=dataclasses.replace(sim.recording, streams=tuple(streams)))
        root.mkdir(parents=True, exist_ok=True)
        if fmt not in ("bin", "log"):
            write_log(sim, path)
            return path
        write_log(sim, binary)
        if patch:
            data = bytearray(binary.read_bytes())
            at, n = MAG_FIELDS
            for pos in parse_binary(binary).tables["MAG"].pos.tolist():
                data[pos + at:pos + at + n] = bytes(n)
            binary.write_bytes(bytes(data))
        if fmt == "log":
            text_log(binary, path)
        return path

    def _values(self, values: Any) -> Any:
        """Zeros, or the first reading repeated, in the shape of `values`."""
        import numpy as np

        return np.zeros_like(values) if self.value == "zero" else np.broadcast_to(values[0], values.shape).copy()


def damaged_copy(seed: Path, mutation: Mutation, work: Path) -> Path:
    """Write the damaged log into `work` (a fresh directory) and return the path to give magcal."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    if seed.is_dir():                                      # a ROS 2 bag: damage its storage file or metadata
        target = work / seed.name
        shutil.copytree(seed, target)
        files = sorted(p for p in target.iterdir() if p.suffix != ".yaml")
        victim = target / "metadata.yaml" if mutation.seed % 8 == 0 else files[0]
        victim.write_bytes(mutation.apply(victim.read_bytes()))
        return target
    target = work / seed.name
    target.write_bytes(mutation.apply(seed.read_bytes()))
    return target


@dataclass(frozen=True)
class Outcome:
    """What one case did: exit code, the category (ok, error, gate, contract violation) and the error line."""

    exit_code: int
    category: str
    message: str


def check_contract(exit_code: int, stdout: str, stderr: str, outdir: Path | None) -> str | None:
    """Why the run broke the command-line contract, or None."""
    if "Traceback" in stdout + stderr:
        return "traceback"
    if exit_code not in (0, 1, 3):
        return f"exit {exit_code}"
    errors = [line for line in stderr.splitlines() if line.startswith("Error:")]
    if exit_code != 0:
        others = [line for line in stderr.splitlines() if line.strip() and not line.startswith(("Error:", "magcal:"))]
        if len(errors) != 1 or "\n" in errors[0] or others:
            return f"expected one Error: line, got {stderr!r}"
    elif errors:
        return f"exit 0 with an error line: {errors[0]!r}"
    if outdir is not None and outdir.exists():
        stray = [p.name for p in outdir.iterdir() if p.name.startswith(".") or p.suffix == ".part"]
        if stray:
            return f"temporary files left: {stray}"
        if exit_code == 0:
            from magcal_cli.calibration.document import load

            load(outdir / "calibration.json")            # raises CalibrationFileError when not valid
            json.loads((outdir / "calibration.json").read_text())
    return None


def run_case(path: Path, mode: str, outdir: Path, invoke: Callable[[list[str]], tuple[int, str, str]]) -> Outcome:
    """Run `magcal inspect` or `magcal fit` on `path` and classify the outcome against the contract."""
    if mode == "inspect":
        args = ["inspect", str(path)]
        out: Path | None = None
    else:
        args = ["fit", str(path), "-o", str(outdir), "--outputs", "json", "-q", "--force"]
        out = outdir
    code, stdout, stderr = invoke(args)
    broken = check_contract(code, stdout, stderr, out)
    if broken:
        return Outcome(code, "violation", broken)
    error = next((line for line in stderr.splitlines() if line.startswith("Error:")), "")
    return Outcome(code, {0: "ok", 1: "error", 3: "gate"}[code], error)


def cli_invoker() -> Callable[[list[str]], tuple[int, str, str]]:
    """A function that runs the magcal CLI in-process and returns (exit code, stdout, stderr)."""
    from click.testing import CliRunner

    from magcal_cli.cli.main import cli

    runner = CliRunner()

    def invoke(args: list[str]) -> tuple[int, str, str]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = runner.invoke(cli, args, catch_exceptions=True)
        stderr = result.stderr + "".join(f"{w.category.__name__}: {w.message} ({Path(w.filename).name}:{w.lineno})\n"
                                         for w in caught)
        if result.exception is not None and not isinstance(result.exception, SystemExit):
            stderr += f"\nTraceback: {type(result.exception).__name__}: {result.exception}"
        return result.exit_code, result.stdout, stderr

    return invoke
