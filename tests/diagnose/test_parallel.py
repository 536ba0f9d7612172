"""The diagnosis on threads: the same digits whatever the number of threads (its folds and replicates run side by
side, and the magnetometers' shared-bias refits)."""

from __future__ import annotations

import json

import pytest

from magcal_cli.calibration.document import dumps_json
from magcal_cli.config import Config
from magcal_cli.diagnose import parallel
from magcal_cli.pipeline import calibrate_recording
from magcal_cli.synth.effects import EffectSpec
from magcal_cli.synth.simulate import simulate


def test_pmap_keeps_order_and_reads_jobs_on_each_call(monkeypatch: pytest.MonkeyPatch) -> None:
    """Results come back in the items' order; MAGCAL_JOBS (`parallel.JOBS`) is read when pmap runs."""
    import threading

    seen: set[str] = set()

    def item(x: int) -> int:
        seen.add(threading.current_thread().name)
        return x * x

    monkeypatch.setattr(parallel, "JOBS", 1)
    assert parallel.pmap(item, list(range(8))) == [x * x for x in range(8)]
    assert seen == {threading.current_thread().name}


def test_two_magnetometers_diagnosed_alike_on_one_thread_and_on_two(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two magnetometers and a lag, diagnosed with MAGCAL_JOBS=1 and =2: every number of the document is the same
    (created_utc aside); both were diagnosed, and the lag was found."""
    sim = simulate("handheld", 5, duration=45.0, rate=100.0, mag_rate=50.0, n_mags=2,
                   effects=(EffectSpec("time_offset", {"tau_s": 0.02}),))
    docs = []
    for jobs in (1, 2):
        monkeypatch.setattr(parallel, "JOBS", jobs)
        doc = json.loads(dumps_json(calibrate_recording(sim.recording, Config(diagnose=True)).calibration))
        doc.pop("created_utc", None)
        docs.append(doc)
    assert docs[0] == docs[1]
    assert [d["sensor"] for d in docs[0]["diagnosis"]["sensors"]] == ["/imu/mag", "/imu/mag1"]
    # the shared-bias refit (map/shared.py) ran, side by side with JOBS = 2
    assert any("one IMU, one bias" in n for n in docs[0]["notes"])
    assert ("time_offset", "/imu/mag", "accepted") in [(e["id"], e["sensor"], e["status"]) for e in docs[0]["effects"]]
