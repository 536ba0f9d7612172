"""Fuzz campaign (issue 6): thousands of damaged logs of every format through `magcal inspect` and `magcal fit`.

    python benchmarks/fuzz_campaign.py [--cases 400] [--fit-share 0.25] [--seed 1] [--formats bin,ulg,...]

Makes one small simulated log per format (tests/fuzzing.py), damages a copy per case (bit flips, byte insertions
and deletions, truncation, chunk duplication, zeroed runs, header damage), runs the CLI in-process and checks the
command-line contract. Prints cases per format and mutation with their outcomes (ok, error, gate, violation) and
every violation with the case that reproduces it. Exit 1 when any case broke the contract. Not a test: 400 cases
per format take about five minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzzing import FORMATS, cli_invoker, damaged_copy, make_seeds, random_mutation, run_case  # noqa: E402


def main() -> int:
    """Run the campaign and print its table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=400, help="cases per format")
    ap.add_argument("--fit-share", type=float, default=0.25, help="share of cases run through fit (else inspect)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--formats", default=",".join(FORMATS))
    args = ap.parse_args()
    rng = random.Random(args.seed)
    invoke = cli_invoker()
    outcomes: Counter[tuple[str, str, str]] = Counter()
    by_op: Counter[tuple[str, str]] = Counter()
    errors: Counter[str] = Counter()
    violations: list[str] = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="magcal-fuzz-") as tmp:
        root = Path(tmp)
        seeds = make_seeds(root / "seeds")
        for fmt in args.formats.split(","):
            t0 = time.perf_counter()
            for _ in range(args.cases):
                mutation = random_mutation(rng)
                mode = "fit" if rng.random() < args.fit_share else "inspect"
                extra = ["--allow-truncated"] if mode == "fit" and rng.random() < 0.5 else []
                path = damaged_copy(seeds[fmt], mutation, root / "log")
                outcome = run_case(path, mode, root / "out", lambda a, e=extra: invoke(a + e))
                outcomes[(fmt, mode, outcome.category)] += 1
                by_op[(mutation.op, outcome.category)] += 1
                if outcome.category == "error":
                    errors[outcome.message.split(": ", 2)[-1][:60]] += 1
                if outcome.category == "violation":
                    violations.append(f"{fmt} {mode} {' '.join(extra)} {mutation}: {outcome.message}")
            print(f"{fmt:5s} {args.cases} cases in {time.perf_counter() - t0:5.1f} s", flush=True)
    total = sum(outcomes.values())
    print(f"\n{total} cases in {time.perf_counter() - start:.0f} s (seed {args.seed})\n")
    print(f"{'format':7s}{'mode':9s}{'cases':>7s}{'ok':>7s}{'error':>7s}{'gate':>6s}{'violation':>11s}")
    for fmt in args.formats.split(","):
        for mode in ("inspect", "fit"):
            row = [outcomes[(fmt, mode, c)] for c in ("ok", "error", "gate", "violation")]
            print(f"{fmt:7s}{mode:9s}{sum(row):7d}{row[0]:7d}{row[1]:7d}{row[2]:6d}{row[3]:11d}")
    print(f"\n{'mutation':10s}{'cases':>7s}{'ok':>7s}{'error':>7s}{'violation':>11s}")
    for op in sorted({op for op, _ in by_op}):
        row = [by_op[(op, c)] for c in ("ok", "error", "violation")]
        print(f"{op:10s}{sum(row) + by_op[(op, 'gate')]:7d}{row[0]:7d}{row[1]:7d}{row[2]:11d}")
    print("\nmost frequent error lines (after the path):")
    for text, n in errors.most_common(12):
        print(f"{n:6d}  {text}")
    print(f"\nviolations (tracebacks, exit 123, stray lines or files): {len(violations)}")
    for v in violations[:50]:
        print("  " + v)
    return 1 if violations else 0


if __name__ == "__main__":
    sys.exit(main())
