"""Heading on real flights against the vehicle's own attitude: magcal, the flown calibration and magfit_WMM (issue 38).

For every ArduPilot (ATT) and PX4 (vehicle_attitude) log in ../shared/realdata/ and its zoo/, and each compass a
default `magcal fit` calibrates: the heading error against the attitude's yaw, computed here from the physics and
independently of magcal's own `heading_check`:
- the calibrated field (body frame) is levelled with the attitude's roll and pitch (ArduPilot: plus AHRS_TRIM_X/Y,
  as magfit_WMM does), its heading is atan2(-h_y, h_x) plus the WMM declination at the log's position and date
  (0 when the log has no position: the mean removal below absorbs any constant), minus the attitude's yaw, wrapped;
- the circular mean of each calibration's error over the evaluated span is removed (a constant misalignment or
  declination is not a heading error the attitude can judge), and the RMS is reported in degrees.

Three calibrations: magcal's (`magcal fit LOG --outputs json`, defaults otherwise, applied with its carried current
or throttle interference), the one the vehicle flew with (the log's parameters, `firmware/flown.py`) and
magfit_WMM's (ArduPilot only, `vs_magfit.run_magfit`: `--elliptical --cmot`, `--reduce N`, rerun with `--iter 1000`
when it stops at its iteration limit). Out of sample: the log is
cut in two halves by time; magcal is also fitted on each half alone (`--start/--end`) and magfit_WMM too (`--condition`
on the compass message's time), and each is judged on the other half. The flown calibration was made before the flight
(out of sample by construction); the whole-log fits of magcal and magfit_WMM are in sample. The paired difference magcal (out of sample) minus flown has a block-jackknife standard error
(contiguous blocks of about 10 s), so "worse" means worse by more than twice that.

    python benchmarks/real_heading.py [--realdata ../shared/realdata] [--out docs/results/real_heading]
                                      [--magfit-reduce 4] [--no-magfit] [--only NAME,...] [--timeout 900]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_logs import ROOT, find_logs, fit_default, git_meta  # noqa: E402

Array = npt.NDArray[np.float64]
#: the attitude stream the vehicle flew with, per format
ATTITUDE = ("ATT", "vehicle_attitude")
TRIMS = ("AHRS_TRIM_X", "AHRS_TRIM_Y")
BLOCK_S = 10.0
#: magfit_WMM --iter after "Iteration limit reached" with its default 100
MAGFIT_ITER = 1000


def heading_error(t: Array, field: Array, att_t: Array, att_q: Array, decl: float, trim: Array) -> tuple[Array, Array]:
    """(times, wrapped heading error rad) of a body-frame field against an attitude stream (quaternion wxyz,
    body->NED); epochs outside the attitude's span, more than 1 s from an attitude sample, or not finite dropped."""
    from magcal_cli import so3

    j = np.clip(np.searchsorted(att_t, t), 1, att_t.size - 1)
    near = np.minimum(np.abs(att_t[j] - t), np.abs(att_t[j - 1] - t))
    ok = (t >= att_t[0]) & (t <= att_t[-1]) & (near <= 1.0) & np.all(np.isfinite(field), axis=1)
    rots = so3.slerp(so3.from_quat(att_q), att_t, t[ok])
    rpy = so3.as_rpy(rots)
    roll, pitch, yaw = rpy[:, 0] + trim[0], rpy[:, 1] + trim[1], rpy[:, 2]
    # level the field: h = Ry(pitch) Rx(roll) m_b (the yaw-free part of body->NED)
    level = so3.from_rpy(np.stack([roll, pitch, np.zeros_like(roll)], axis=1))
    h = np.einsum("nij,nj->ni", level, field[ok])
    psi = np.arctan2(-h[:, 1], h[:, 0]) + decl
    return t[ok], np.angle(np.exp(1j * (psi - yaw)))


def demeaned(err: Array) -> Array:
    """Heading errors (rad) with their circular mean removed, wrapped."""
    if err.size == 0:
        return err
    out: Array = np.angle(np.exp(1j * (err - np.angle(np.mean(np.exp(1j * err))))))
    return out


def rms_deg(err: Array) -> float | None:
    """RMS (deg) of heading errors (rad); None for none."""
    return float(np.degrees(np.sqrt(np.mean(err**2)))) if err.size else None


def paired(t: Array, a: Array, b: Array) -> dict[str, float] | None:
    """RMS(a) - RMS(b) (deg) over common epochs (a, b demeaned heading errors at times t) and its block-jackknife
    standard error (contiguous blocks of about BLOCK_S s, at least 8, so correlated errors are not counted as
    independent)."""
    if t.size < 16:
        return None
    n_blocks = int(max(8, min(40, (t[-1] - t[0]) // BLOCK_S)))
    block = np.minimum(((t - t[0]) / (t[-1] - t[0] + 1e-9) * n_blocks).astype(int), n_blocks - 1)

    def diff(keep: npt.NDArray[np.bool_]) -> float:
        return float(np.degrees(np.sqrt(np.mean(a[keep] ** 2)) - np.sqrt(np.mean(b[keep] ** 2))))

    full = diff(np.ones(t.size, dtype=bool))
    loo = np.array([diff(block != k) for k in range(n_blocks) if np.any(block == k)])
    se = float(np.sqrt((loo.size - 1) / loo.size * np.sum((loo - loo.mean()) ** 2)))
    return {"diff_deg": full, "se_deg": se, "blocks": int(loo.size)}


def on_common(series: dict[str, tuple[Array, Array]], keys: tuple[str, str], lo: float, hi: float
              ) -> tuple[Array, Array, Array]:
    """Two calibrations' raw (not demeaned) errors on the epochs in [lo, hi) both have, by time."""
    (ta, ea), (tb, eb) = series[keys[0]], series[keys[1]]
    t, ia, ib = np.intersect1d(ta, tb, return_indices=True)
    keep = (t >= lo) & (t < hi)
    return t[keep], ea[ia][keep], eb[ib][keep]


def log_context(log: Path) -> dict[str, Any] | str:
    """The recording, its attitude stream, declination (rad), AHRS trim and the halves' boundary; why not, when the
    log cannot be read or has no attitude stream the vehicle flew with or no magnetometer."""
    from magcal_cli.config import Config
    from magcal_cli.errors import MagcalError
    from magcal_cli.pipeline import with_position
    from magcal_cli.readers import ReadOptions, open_recording
    from magcal_cli.streams import Kind
    from magcal_cli.wmm import reference_for

    try:
        rec = open_recording(log, None, ReadOptions(allow_truncated=True))
    except Exception as exc:  # noqa: BLE001 - reported in the table, not a reason to stop the benchmark
        return f"not read: {type(exc).__name__}: {exc}"
    att = [s for s in rec.of_kind(Kind.ATTITUDE) if s.id in ATTITUDE and len(s) >= 2]
    if not att:
        return "no ATT or vehicle_attitude stream"
    if not rec.of_kind(Kind.MAGNETOMETER):
        return "no magnetometer stream"
    try:
        ref = reference_for(with_position(rec, Config()))
    except MagcalError:
        ref = None
    end = max(float(s.t[-1]) for s in rec.streams if len(s))
    trim = np.array([rec.params.get(k, 0.0) for k in TRIMS]) if rec.format == "dataflash" else np.zeros(2)
    return {"rec": rec, "att": att[0], "decl": ref.declination if ref else 0.0, "wmm": ref is not None,
            "trim": trim, "end": end, "half": end / 2.0}


def fields(ctx: dict[str, Any], mag_id: str, docs: dict[str, dict[str, Any] | None],
           magfit: dict[str, dict[str, Any]]) -> dict[str, tuple[Array, Array]]:
    """Each calibration's body-frame field of one compass: flown, magcal and magfit_WMM (whole log, each half)."""
    from magcal_cli.calibration.document import from_dict
    from magcal_cli.errors import MagcalError
    from magcal_cli.firmware.flown import flown_fields

    rec = ctx["rec"]
    out: dict[str, tuple[Array, Array]] = {}
    try:
        f = flown_fields(rec, [mag_id], None, None)[0][0]
        out["flown"] = (f.t, f.field)
    except MagcalError:
        pass
    for name, doc in docs.items():
        if doc is None or mag_id not in {m.get("id") for m in doc.get("magnetometers", [])}:
            continue
        try:
            f = flown_fields(rec, [mag_id], None, from_dict(doc))[0][0]
        except MagcalError:
            continue
        out[name] = (f.t, f.field)
    from vs_magfit import magfit_field

    for name, res in magfit.items():
        if "error" not in res:
            out[name] = magfit_field(rec, mag_id, res)
    return out


def compass_rows(ctx: dict[str, Any], mag_id: str, fld: dict[str, tuple[Array, Array]]) -> dict[str, Any]:
    """Per half: each calibration's heading RMS (magcal out of sample = the other half's fit), and the paired
    differences with their standard errors."""
    att = ctx["att"]
    raw = {k: heading_error(t, f, att.t, att.values, ctx["decl"], ctx["trim"]) for k, (t, f) in fld.items()}
    halves = ((0.0, ctx["half"]), (ctx["half"], ctx["end"] + 1.0))
    row: dict[str, Any] = {"id": mag_id, "halves": []}
    oos_t, oos_m, oos_f = [], [], []
    pooled: dict[str, list[Array]] = {}
    oos_series: list[tuple[dict[str, tuple[Array, Array]], tuple[float, float]]] = []
    for k, (lo, hi) in enumerate(halves):
        series = dict(raw)
        for tool in ("magcal", "magfit"):
            if f"{tool}_half{2 - k}" in raw:       # fitted on the other half
                series[f"{tool}_oos"] = raw[f"{tool}_half{2 - k}"]
        rms: dict[str, float | None] = {}
        for name in ("flown", "magcal_oos", "magfit_oos", "magcal", "magfit_WMM"):
            if name in series:
                t, e = series[name]
                pooled.setdefault(name, []).append(demeaned(e[(t >= lo) & (t < hi)]))
                rms[name] = rms_deg(pooled[name][-1])
        half: dict[str, Any] = {"span_s": [round(lo, 1), round(min(hi, ctx["end"]), 1)], "rms_deg": rms}
        if "magcal_oos" in series and "flown" in series:
            t, a, b = on_common(series, ("magcal_oos", "flown"), lo, hi)
            a, b = demeaned(a), demeaned(b)
            half["oos_minus_flown"] = paired(t, a, b)
            oos_t.append(t)
            oos_m.append(a)
            oos_f.append(b)
        if "magcal_oos" in series and "magfit_oos" in series:
            t, a, b = on_common(series, ("magcal_oos", "magfit_oos"), lo, hi)
            half["oos_minus_magfit"] = paired(t, demeaned(a), demeaned(b))
        row["halves"].append(half)
        oos_series.append((series, (lo, hi)))
    if oos_t:
        row["oos_minus_flown"] = paired(np.concatenate(oos_t), np.concatenate(oos_m), np.concatenate(oos_f))
    both = [on_common(series_k, ("magcal_oos", "magfit_oos"), lo, hi) for series_k, (lo, hi) in oos_series
            if "magcal_oos" in series_k and "magfit_oos" in series_k]
    if both:
        row["oos_minus_magfit"] = paired(np.concatenate([b[0] for b in both]),
                                         np.concatenate([demeaned(b[1]) for b in both]),
                                         np.concatenate([demeaned(b[2]) for b in both]))
    # both halves: each half's errors demeaned on their own, as in the rows above, then pooled
    row["both_rms_deg"] = {k: rms_deg(np.concatenate(v)) for k, v in pooled.items()}
    return row


def run_log(log: Path, realdata: Path, args: argparse.Namespace) -> dict[str, Any]:
    """The fits (whole log, each half), magfit_WMM per calibrated compass (ArduPilot) and the heading rows; or why
    the log was skipped."""
    from magcal_cli.streams import Kind

    name = str(log.relative_to(realdata))
    ctx = log_context(log)
    if isinstance(ctx, str):
        print(f"{name}: skipped, {ctx}", flush=True)
        return {"log": name, "skipped": ctx}
    t0 = time.perf_counter()
    half = f"{ctx['half']:.3f}"
    runs = {"magcal": fit_default(log, args.timeout, ("--outputs", "json")),
            "magcal_half1": fit_default(log, args.timeout, ("--outputs", "json", "--end", half)),
            "magcal_half2": fit_default(log, args.timeout, ("--outputs", "json", "--start", half))}
    docs = {k: (r["document"] if r["exit"] == 0 else None) for k, r in runs.items()}
    full = docs["magcal"] or {}
    calibrated = [m["id"] for m in full.get("magnetometers", [])]
    all_mags = ctx["rec"].ids(Kind.MAGNETOMETER)
    row: dict[str, Any] = {"log": name, "attitude": ctx["att"].id, "wmm_declination": ctx["wmm"],
                           "decl_deg": float(np.degrees(ctx["decl"])), "half_s": ctx["half"],
                           "exits": {k: r["exit"] for k, r in runs.items()},
                           "fit_s": {k: round(r["seconds"], 1) for k, r in runs.items()},
                           "not_calibrated": [m for m in all_mags if m not in calibrated], "compasses": []}
    for mag_id in calibrated:
        magfit = {}
        if ctx["rec"].format == "dataflash" and not args.no_magfit:      # magfit_WMM reads ArduPilot logs only
            magfit = run_magfits(log, ctx, all_mags.index(mag_id) + 1, args)
            row.setdefault("magfit_s", {})[mag_id] = {k: r["seconds"] for k, r in magfit.items()}
            row.setdefault("magfit_points", {})[mag_id] = {k: r.get("points") for k, r in magfit.items()}
            for k, r in magfit.items():
                if "error" in r or r.get("retried_iter"):
                    row.setdefault("magfit_error", {})[f"{mag_id} {k}"] = (
                        f"{r['error']} (also with --iter {MAGFIT_ITER})" if "error" in r
                        else f"converged only with --iter {MAGFIT_ITER}")
        comp = compass_rows(ctx, mag_id, fields(ctx, mag_id, docs, magfit))
        m = next(m for m in full["magnetometers"] if m["id"] == mag_id)
        comp["method"] = m.get("method") or full.get("method")
        # the EKF steers by the primary compass, so ATT's yaw leans towards the flown calibration there
        comp["role"] = ("primary" if int(ctx["rec"].params.get("COMPASS_PRIMARY", 0)) == all_mags.index(mag_id)
                        else "secondary") if ctx["rec"].format == "dataflash" else None
        comp["heading_check"] = m.get("heading_check")
        row["compasses"].append(comp)
    row["seconds"] = round(time.perf_counter() - t0, 1)
    print(f"{name}: {row['seconds']} s, {len(calibrated)} calibrated", flush=True)
    return row


def run_magfits(log: Path, ctx: dict[str, Any], mag: int, args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """magfit_WMM on the whole log and on each half (`--condition` on the compass message's own clock, the
    reader's t0 added back), as vs_magfit runs it (retried with --att-source ATT after a crash)."""
    from vs_magfit import run_magfit

    msg = "MAG" if mag == 1 else f"MAG{mag}"
    clock = f"getattr({msg}, 'TimeUS', getattr({msg}, 'TimeMS', 0) * 1000) * 1e-6"
    cut = ctx["rec"].t0 + ctx["half"]
    out = {}
    for name, more in (("magfit_WMM", ()), ("magfit_half1", ("--condition", f"{clock} < {cut:.3f}")),
                       ("magfit_half2", ("--condition", f"{clock} >= {cut:.3f}"))):
        run = run_magfit(str(log), mag, args.magfit_reduce, args.timeout, more)
        seconds = sum(a["seconds"] for a in run["attempts"])
        if "Iteration limit" in run["result"].get("error", ""):
            # what a user does next: more SLSQP iterations than magfit_WMM's 100
            retry = run_magfit(str(log), mag, args.magfit_reduce, args.timeout, (*more, "--iter", str(MAGFIT_ITER)))
            seconds += sum(a["seconds"] for a in retry["attempts"])
            run = retry | {"first_error": run["result"]["error"]}
        out[name] = run["result"] | {"seconds": round(seconds, 1), "retried_iter": "first_error" in run}
    return out


def _method(c: dict[str, Any]) -> str:
    """The method that calibrated a compass, and whether the vehicle's EKF steered by it (ArduPilot)."""
    return str(c["method"]) + (f" ({c['role']})" if c.get("role") else "")


def _check(hc: Any) -> str:
    """magcal's own heading_check block in a few words: its RMS for magcal and flown, difference ± std, verdict."""
    if not isinstance(hc, dict):
        return ""
    rms = hc.get("rms_deg") or {}
    try:
        return (f"{rms['magcal']:.2f} vs flown {rms['flown']:.2f}: {hc['difference_deg']:+.2f} ± "
                f"{hc['difference_std_deg']:.2f} ({hc.get('verdict')}, {hc.get('folds')} folds)")
    except (KeyError, TypeError, ValueError):
        return _cell_text(json.dumps(hc))


def _cell_text(text: str) -> str:
    """A document excerpt for a table cell: pipes escaped, at most 100 characters."""
    return text.replace("|", "\\|")[:100]


def _num(v: float | None) -> str:
    """A number of degrees for the table, or n/a."""
    return "n/a" if v is None else f"{v:.2f}"


def _diff(p: dict[str, float] | None) -> str:
    """A paired difference with its standard error and what it says (beyond 2 SE)."""
    if p is None:
        return "n/a"
    verdict = "worse" if p["diff_deg"] > 2 * p["se_deg"] else "better" if p["diff_deg"] < -2 * p["se_deg"] else "tie"
    return f"{p['diff_deg']:+.2f} ± {p['se_deg']:.2f} ({verdict})"


def markdown(rows: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """The page: what was run, the tally, then one line per compass and half and one for both halves."""
    skipped = [r for r in rows if "skipped" in r]
    rows = [r for r in rows if "skipped" not in r]
    comps = [c for r in rows for c in r["compasses"]]
    pooled = [c.get("oos_minus_flown") for c in comps]
    worse = sum(p is not None and p["diff_deg"] > 2 * p["se_deg"] for p in pooled)
    better = sum(p is not None and p["diff_deg"] < -2 * p["se_deg"] for p in pooled)
    na = sum(p is None for p in pooled)
    head = (f"# Heading on real flights against the vehicle's own attitude\n\n"
            f"Made by `{meta['command']}` on {meta['date']} at {meta['commit']}{meta['dirty']}; {meta['seconds']:.0f} s "
            f"in all. {len(rows)} logs with an ATT or vehicle_attitude stream, {len(comps)} compasses calibrated by a "
            f"default fit. magfit_WMM: `--elliptical --cmot --reduce {meta['magfit_reduce']}` "
            f"({'skipped' if meta['no_magfit'] else 'ArduPilot only; PX4: n/a'}).\n\n"
            f"**magcal out of sample vs flown (both halves pooled): worse beyond 2 SE on {worse}, better on {better}, "
            f"tie on {len(comps) - worse - better - na}, n/a on {na}** (n/a: a half's fit did not calibrate the compass, "
            "or the log has no flown calibration).\n\n" + (__doc__ or "").split("\n\n", 1)[1].split("\n\n    python")[0]
            + "\n\nColumns: heading error RMS in degrees, mean removed per half. *magcal OOS*: the fit on the other half "
            "alone; *magfit_WMM OOS* likewise. *magcal*, *magfit_WMM*: the whole-log fits (in sample); *both*: the two "
            "halves pooled. Differences: RMS(first) - RMS(second) on the "
            "epochs both have, ± block-jackknife SE; worse/better when beyond 2 SE. *heading_check*: magcal's own "
            "block of the document, where present (to compare).\n\n")
    lines = ["| log | compass | method | half (s) | flown | magcal OOS | magfit_WMM OOS | magcal | magfit_WMM | "
             "magcal OOS - flown | magcal OOS - magfit_WMM OOS | heading_check |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for i, c in enumerate(r["compasses"]):
            for k, h in enumerate(c["halves"]):
                rms = h["rms_deg"]
                hc = _check(c.get("heading_check")) if k == 0 else ""
                lines.append(f"| {r['log'] if i == 0 and k == 0 else ''} | {c['id'] if k == 0 else ''} | "
                             f"{_method(c) if k == 0 else ''} | {h['span_s'][0]:.0f}-{h['span_s'][1]:.0f} | "
                             f"{_num(rms.get('flown'))} | {_num(rms.get('magcal_oos'))} | "
                             f"{_num(rms.get('magfit_oos'))} | {_num(rms.get('magcal'))} | "
                             f"{_num(rms.get('magfit_WMM'))} | {_diff(h.get('oos_minus_flown'))} | "
                             f"{_diff(h.get('oos_minus_magfit'))} | {hc} |")
            w = c.get("both_rms_deg", {})
            lines.append(f"| | | | both | {_num(w.get('flown'))} | {_num(w.get('magcal_oos'))} | "
                         f"{_num(w.get('magfit_oos'))} | {_num(w.get('magcal'))} | {_num(w.get('magfit_WMM'))} | "
                         f"{_diff(c.get('oos_minus_flown'))} | {_diff(c.get('oos_minus_magfit'))} | |")
        if r["not_calibrated"]:
            lines.append(f"| {r['log'] if not r['compasses'] else ''} | {', '.join(r['not_calibrated'])} | not "
                         f"calibrated by the default fit (exit {r['exits']['magcal']}) | | | | | | | | | |")
    errors = [f"- {r['log']} {m}: {e}" for r in rows for m, e in r.get("magfit_error", {}).items()]
    times = [f"- {r['log']}: {r['seconds']} s (magcal fits {r['fit_s']}; magfit_WMM {r.get('magfit_s', 'n/a')})"
             for r in rows]
    skips = [f"- {r['log']}: {r['skipped']}" for r in skipped]
    return head + "\n".join(lines) + "\n\n## Logs not compared\n\n" + "\n".join(skips) + "\n\n## Times\n\n" + "\n".join(times) + "\n" + \
        ("\n## magfit_WMM failures and retries\n\n" + "\n".join(errors) + "\n" if errors else "")


def main() -> None:
    """Run every log with an attitude stream, print and save the table (OUT.md, OUT.json)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--realdata", type=Path, default=ROOT.parent / "shared" / "realdata")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "real_heading",
                    help="writes OUT.md and OUT.json")
    ap.add_argument("--magfit-reduce", type=int, default=4, help="magfit_WMM --reduce (1: every reading)")
    ap.add_argument("--no-magfit", action="store_true", help="skip magfit_WMM")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per fit")
    ap.add_argument("--only", default="", help="comma-separated substrings: run only the logs whose path has one")
    ap.add_argument("--render", action="store_true", help="only rewrite OUT.md (and print it) from OUT.json")
    args = ap.parse_args()
    if args.render:
        saved = json.loads(args.out.with_suffix(".json").read_text())
        args.out.with_suffix(".md").write_text(page := markdown(saved["logs"], saved["meta"]))
        print(page)
        return
    if not args.realdata.is_dir():
        print(f"{args.realdata}: no real logs here; nothing to measure")
        return
    logs = find_logs(args.realdata)
    if args.only:
        logs = [p for p in logs if any(s in str(p) for s in args.only.split(","))]
    t0 = time.perf_counter()
    rows = [run_log(p, args.realdata, args) for p in logs]
    meta = {"command": "python benchmarks/real_heading.py " + " ".join(sys.argv[1:]),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "seconds": time.perf_counter() - t0,
            "magfit_reduce": args.magfit_reduce, "no_magfit": args.no_magfit, **git_meta()}
    page = markdown(rows, meta)
    print(page)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"meta": meta, "logs": rows}, indent=1, default=str) + "\n")
    args.out.with_suffix(".md").write_text(page)


if __name__ == "__main__":
    main()
