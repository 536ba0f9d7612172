"""Fuzzing (issue 6): hypothesis-driven damage to a small log of every format, run through the CLI in-process.

Every case must end with exit 0 (and a calibration document that loads) or exit 1/3 with exactly one `Error:`
line: never a traceback, never exit 123, never a temporary file left behind. 280 `inspect` cases and 42 `fit`
cases here (about 40 s on 2 cores); benchmarks/fuzz_campaign.py runs thousands.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from .fuzzing import (
    DEAD_FORMATS,
    DEAD_KINDS,
    DEAD_MESSAGE,
    DEAD_VALUES,
    FORMATS,
    MUTATIONS,
    DeadSensor,
    Mutation,
    cli_invoker,
    damaged_copy,
    make_seeds,
    run_case,
)

MUTATION = st.builds(Mutation, op=st.sampled_from(MUTATIONS), where=st.floats(0.0, 1.0, exclude_max=True),
                     length=st.sampled_from([1, 2, 4, 8, 37, 64, 300]), seed=st.integers(0, 2**30))
SETTINGS = {"deadline": None, "derandomize": True, "database": None,
            "suppress_health_check": [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]}


@pytest.fixture(scope="session")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One small simulated log per format (made once per test session)."""
    return make_seeds(tmp_path_factory.mktemp("fuzz-seeds"))


@pytest.fixture(scope="session")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A scratch directory reused by every case."""
    return tmp_path_factory.mktemp("fuzz-work")


@pytest.fixture(scope="session")
def invoke() -> Callable[[list[str]], tuple[int, str, str]]:
    """The magcal CLI, in-process."""
    return cli_invoker()


def check(seeds: dict[str, Path], work: Path, invoke: Callable[[list[str]], tuple[int, str, str]], fmt: str,
          mutation: Mutation, mode: str, extra: tuple[str, ...] = ()) -> None:
    """Damage the seed of `fmt`, run magcal and fail with the case when the contract is broken."""
    path = damaged_copy(seeds[fmt], mutation, work / "log")
    outcome = run_case(path, mode, work / "out", lambda args: invoke(args + list(extra)))
    assert outcome.category != "violation", f"{fmt} {mutation} {mode} {extra}: {outcome.message}"


@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=40, **SETTINGS)
@given(mutation=MUTATION)
def test_inspect_survives_damage(seeds: dict[str, Path], work: Path,
                                 invoke: Callable[[list[str]], tuple[int, str, str]], fmt: str,
                                 mutation: Mutation) -> None:
    """`magcal inspect` on a damaged log: a listing or one Error: line."""
    check(seeds, work, invoke, fmt, mutation, "inspect")


@pytest.mark.parametrize("fmt", FORMATS)
@settings(max_examples=6, **SETTINGS)
@given(mutation=MUTATION, strict=st.booleans())
def test_fit_survives_damage(seeds: dict[str, Path], work: Path, invoke: Callable[[list[str]], tuple[int, str, str]],
                             fmt: str, mutation: Mutation, strict: bool) -> None:
    """`magcal fit` on a damaged log: a calibration document that loads, or one Error: line."""
    check(seeds, work, invoke, fmt, mutation, "fit", ("--strict",) if strict else ())


@pytest.mark.parametrize("fmt", FORMATS)
def test_undamaged_seeds_calibrate(seeds: dict[str, Path], work: Path,
                                   invoke: Callable[[list[str]], tuple[int, str, str]], fmt: str) -> None:
    """The seeds themselves calibrate, so a damaged copy that fails fails because of the damage."""
    outcome = run_case(seeds[fmt], "fit", work / "clean", invoke)
    assert outcome.category == "ok", outcome.message


@pytest.mark.parametrize("fmt", DEAD_FORMATS)
@pytest.mark.parametrize("value", DEAD_VALUES)
@pytest.mark.parametrize("kind", DEAD_KINDS)
def test_dead_sensor_is_the_dead_sensor_error(work: Path, invoke: Callable[[list[str]], tuple[int, str, str]],
                                              fmt: str, value: str, kind: str) -> None:
    """A sensor reading zero or a constant throughout: exit 1 with the dead-sensor error, in every format
    (issue 12: an ArduPilot log whose MAG fields were all zero exited 123)."""
    path = DeadSensor(kind, value).write(fmt, work / "dead" / f"{kind}-{value}-{fmt}")
    outcome = run_case(path, "fit", work / "dead-out", invoke)
    assert outcome.category == "error", outcome
    assert outcome.message.endswith(f"{DEAD_MESSAGE} (or the column is a placeholder). Check the sensor and its "
                                    "logging, and record again"), outcome.message
    assert kind in outcome.message
