"""Joint MAP calibration on real BROAD trials (Laidig et al. 2021; ../shared/realdata/broad/).

Undisturbed trials: the factory-calibrated magnetometer should come out with b ~ 0 and a near-identity shape.
Attached-magnet trials (the magnet window only): the calibrated field norm should be constant and the heading
computed with the motion-capture orientation steadier than with the raw readings.

    python benchmarks/broad_realdata.py [--folder ../shared/realdata/broad]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from magcal_cli import so3
from magcal_cli.config import Config
from magcal_cli.pipeline import calibrate
from magcal_cli.streams import Kind

ROOT = Path(__file__).resolve().parents[1]
#: trial -> (start, end) s; the magnet trials are cut to the magnet window (~40-95 s, edges approximate)
TRIALS = {
    "01_undisturbed_slow_rotation_A.mat": (None, None),
    "02_undisturbed_slow_rotation_B.hdf5": (None, None),
    "06_undisturbed_fast_rotation_A.mat": (None, None),
    "32_disturbed_attached_magnet_1cm.hdf5": (45.0, 90.0),
    "33_disturbed_attached_magnet_2cm.hdf5": (45.0, 90.0),
}


def circular_std_deg(angles: np.ndarray) -> float:
    """Circular standard deviation (deg) of angles in rad: sqrt(-2 ln R)."""
    r = float(np.abs(np.mean(np.exp(1j * angles))))
    return float(np.degrees(np.sqrt(-2.0 * np.log(max(r, 1e-300)))))


def headings(m_b: np.ndarray, t_mag: np.ndarray, att_t: np.ndarray, att_q: np.ndarray) -> np.ndarray:
    """Magnetic heading (rad) of the body-frame field m_b rotated into NED with the mocap attitude."""
    idx = np.searchsorted(att_t, t_mag)
    ok = (idx < att_t.size) & (np.abs(att_t[np.minimum(idx, att_t.size - 1)] - t_mag) < 1e-6)
    rot = so3.from_quat(att_q[idx[ok]])
    m_n = np.einsum("nij,nj->ni", rot, m_b[ok])
    return np.arctan2(m_n[:, 1], m_n[:, 0])


def smooth_norm_range_pct(norm: np.ndarray, width: int) -> float:
    """Peak-to-peak (5-95 %) of the moving-average field norm relative to its mean, in %."""
    avg = np.convolve(norm, np.ones(width) / width, mode="valid")
    lo, hi = np.percentile(avg, [5, 95])
    return float(100.0 * (hi - lo) / np.mean(norm))


def main() -> None:
    """Calibrate every trial and print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--folder", type=Path, default=ROOT.parent / "shared" / "realdata" / "broad")
    args = ap.parse_args()
    print(f"{'trial':40} {'time s':>6} {'|b| uT':>7} {'b (uT)':>24} {'|P/F-I|max':>10} {'norm RMS %':>10} "
          f"{'norm 5-95% (0.5 s avg)':>22} {'heading std raw -> cal (deg)':>29} {'dip':>6}")
    for name, (start, end) in TRIALS.items():
        path = args.folder / name
        if not path.exists():
            print(f"{name:40} missing")
            continue
        t0 = time.perf_counter()
        res = calibrate(path, Config(method="map", start_s=start, end_s=end))
        elapsed = time.perf_counter() - t0
        mag = res.calibration.magnetometers[0]
        series = res.series[mag.id]
        att = res.recording.select(Kind.ATTITUDE)
        raw_m = series.raw                                   # factory-calibrated field, uT
        cal_m = series.calibrated * mag.field_strength
        norm = np.linalg.norm(cal_m, axis=1)
        rate = 1.0 / float(np.median(np.diff(series.t)))
        h_raw = headings(raw_m, series.t, att.t, att.values)
        h_cal = headings(cal_m, series.t, att.t, att.values)
        shape = float(np.abs(mag.soft_iron - np.eye(3)).max())
        smooth = smooth_norm_range_pct(norm, int(0.5 * rate))
        print(f"{name:40} {elapsed:6.1f} {np.linalg.norm(mag.b):7.3f} "
              f"[{', '.join(f'{x:+6.2f}' for x in mag.b)}] {shape:10.4f} "
              f"{100 * np.std(norm) / np.mean(norm):10.2f} {smooth:22.2f} "
              f"{circular_std_deg(h_raw):14.2f} -> {circular_std_deg(h_cal):8.2f}    {mag.dip_deg:6.2f}")


if __name__ == "__main__":
    main()
