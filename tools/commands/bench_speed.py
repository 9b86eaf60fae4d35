"""``uuomocap bench speed``: the near-online sliding-window solver against the offline solver on the
same sessions.

For every session (generated deterministically into the benchmark cache unless --session is
given): the windowed solver is fed frame by frame with the frames arriving on the capture clock
after its bootstrap (as the ``solver`` node sees a live 120 Hz stream), and the offline staged
solver (method ``uuo``) solves the whole session.  Printed per session and on average:
  * steady-state throughput: frames after the bootstrap / time spent solving them (frames/s)
    and the real-time factor (throughput / capture rate; >= 1 keeps up);
  * latency arrival -> estimate (p50/p95), arrival -> refined (the fixed lag plus up to one hop of
    the smoothing pass, + processing; p95), a frame's arrival being its time on the capture clock
    (a frame that waits while the solver is behind counts the wait);
  * the same latencies from a queue model: the measured time of every call, served one at a time
    at the capture rate - the solver's own cost, without the waits for a core that a shared
    machine adds (on this 2-core machine those vary by a third from minute to minute);
  * frames/s is wall-clock (what the machine gave us) and per CPU-second of the solver process
    (what a free core gives; the machine is shared);
  * bootstrap seconds (the offline solver on the first seconds);
  * MPJPE / MPJVE of the refined and estimate outputs next to the offline solver's.
Then a long take: a session looped back and forth for --long-minutes (default 10) at a modest
rate, printing peak RSS and the solver's buffer sizes after 1 minute and at the end (flat
memory: nothing grows with the take), and the live fixed-lag output's MPJPE minute by minute
(does it approach the offline solve as lock upgrades land?).  Targets (issue 6): >= 120 frames/s with 40 markers,
estimate p95 <= 30 ms, bootstrap <= 10 s, refined MPJPE within 10 % of offline.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError

TARGET_FPS = 120.0
TARGET_P95_MS = 30.0
TARGET_BOOTSTRAP_S = 10.0


def _sessions(args) -> list[Path]:
    if args.session:
        out = [Path(s) for s in args.session]
        for s in out:
            if not (s / "session.yaml").is_file():
                raise UserError(f"{s}: not a session directory (no session.yaml)")
        return out
    from dataclasses import replace

    from uuomocap.commands.bench_accuracy import default_cache, ensure_session
    from uuomocap.synth import SampleConfig

    cache = Path(args.cache) if args.cache else default_cache()
    base = SampleConfig(rate_hz=args.rate, duration_s=args.duration, n_markers=args.markers, video=False)
    motions = ("walk", "jump", "arms")
    cfgs = [replace(base, motion=motions[i % len(motions)], seed=i) for i in range(args.sessions)]
    return [ensure_session(cache, c) for c in cfgs]


def _pct(values, q) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if len(v) else float("nan")


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _proc_memory_mib(pid: int | str = "self") -> dict:
    """Resident memory of a process now (VmRSS) and its peak (VmHWM), MiB; {} where /proc has
    no such process.  The peak is over the process's life (here: the offline solves before the
    long take), so flat memory shows in the resident size now, measured at both marks."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in ("VmRSS", "VmHWM"):
                    out["rss_mib" if key == "VmRSS" else "peak_mib"] = round(int(value.split()[0]) / 1024.0, 1)
    except (FileNotFoundError, ProcessLookupError, ValueError):
        pass
    return out


def bench_session(sdir: Path, offline: bool, bar) -> dict:
    from uuomocap.solver_core.metrics import mpjpe, mpjve
    from uuomocap.window_methods import estimate_metrics, queue_latencies, session_stream, stream_solve

    md, _, _, _, gt = session_stream(sdir)
    T = md.positions.shape[0]
    bar.set_postfix_str(f"window {sdir.name[:24]}")
    from dataclasses import replace

    from uuomocap.solver_core.windowed_solver import WindowedSolverConfig

    # as the live launch files run it: lock upgrades in the worker process beside the estimates
    run = stream_solve(sdir, realtime=True, config=replace(WindowedSolverConfig(), upgrade_in_background=True))
    lag_ms = 1000.0 * run.stats.get("lag_frames", 10) / run.rate_hz
    queue_est, queue_ref = queue_latencies(run)
    res = {
        "session": str(sdir), "frames": T, "rate_hz": run.rate_hz, "markers": int(md.positions.shape[1]),
        "steady_fps": run.steady_fps, "realtime_factor": run.steady_fps / run.rate_hz, "steady_fps_cpu": run.steady_fps_cpu,
        "bootstrap_s": run.bootstrap_s,
        "estimate_latency_ms": {"p50": _pct(run.latency_estimate_ms, 50), "p95": _pct(run.latency_estimate_ms, 95),
                                "p99": _pct(run.latency_estimate_ms, 99), "max": _pct(run.latency_estimate_ms, 100)},
        "refined_latency_ms": {"lag": lag_ms, "p50": _pct(run.latency_refined_ms, 50), "p95": _pct(run.latency_refined_ms, 95),
                               "p95_minus_lag": _pct(run.latency_refined_ms, 95) - lag_ms},
        # the same stream as a single-server queue over the measured per-call times (the solver's
        # own cost, without the waits for a core on a shared machine: window_methods.queue_latencies)
        "queue_model_ms": {"estimate_p95": _pct(queue_est, 95), "refined_p95_minus_lag": _pct(queue_ref, 95) - lag_ms},
        "rebootstraps": run.stats.get("rebootstraps", 0),
        # Stage-5 marker fit (mm) of each bootstrap start and the index of the one locked
        "bootstrap_start_fits_mm": run.stats.get("bootstrap_start_fits_mm"), "bootstrap_start_chosen": run.stats.get("bootstrap_start_chosen"),
        # the end-of-take revision (WindowedSolverConfig.revise_at_end): seconds the flush spent on it
        "revise_at_end_s": run.stats.get("revise_at_end_s", float("nan")),
        # the end-of-take lock upgrade before it (WindowedSolverConfig.upgrade_at_end_growth)
        "upgrade_at_end_s": run.stats.get("upgrade_at_end_s", float("nan")),
        "lock_upgrades_started": run.stats.get("upgrades_started", 0), "lock_upgrades": run.stats.get("upgrades", 0), "lock_upgrade_s": run.stats.get("upgrade_seconds", []),
    }
    if gt is not None:
        res.update(estimate_metrics(run, gt, "estimate"))
        res.update(estimate_metrics(run, gt, "refined"))
        # what a recording of the stream holds: revised frames where an upgrade landed in the take
        res.update(estimate_metrics(run, gt, "recording"))
        res["revised_frames"] = int(np.isfinite(run.revised["poses"]).all(axis=1).sum()) if run.revised else 0
    if offline:
        import torch

        from uuomocap.solver_methods import inputs_from_session, run_staged_solver

        bar.set_postfix_str(f"offline {sdir.name[:24]}")
        torch.set_num_threads(1)
        t0 = time.perf_counter()
        result, _ = run_staged_solver(inputs_from_session(sdir), "uuo")
        res["offline_s"] = time.perf_counter() - t0
        res["offline_fps"] = T / res["offline_s"]
        if gt is not None:
            gj = np.asarray(gt["joints"])[:T]
            res["offline_mpjpe"] = mpjpe(result.joints, gj)
            res["offline_mpjve"] = mpjve(result.joints, gj, run.rate_hz)
    return res


def add_refined_errors(by_minute: dict, results, gt_joints: np.ndarray, rate_hz: float) -> None:
    """Append each refined result's per-frame MPJPE (metres) to ``by_minute[minute of its frame]``.
    gt_joints: (P,24,3) the true joints of the take's frames, frame k at ``k % P`` (a looped take)."""
    for r in results:
        if r.kind == "refined":
            err = float(np.linalg.norm(np.asarray(r.joints) - gt_joints[r.frame_index % len(gt_joints)], axis=-1).mean())
            by_minute.setdefault(int(r.frame_index / rate_hz // 60), []).append(err)


def long_take(sdir: Path, minutes: float, rate_hz: float, bar) -> dict:
    """Loop a session back and forth (continuous motion) for ``minutes`` at ``rate_hz``."""
    from dataclasses import replace

    import torch

    from uuomocap.solver_core.body_model import load_solver_models as load_models
    from uuomocap.solver_core.windowed_solver import WindowedSolver, WindowedSolverConfig
    from uuomocap.window_methods import session_stream

    torch.set_num_threads(1)
    md, rows, up_axis, body_model, gt = session_stream(sdir)
    step = max(1, int(round(md.rate_hz / rate_hz)))
    # the live output's accuracy minute by minute: the refined frames against the source frames' truth
    gt_joints = np.asarray(gt["joints"])[::step] if gt is not None else None
    minute_err: dict[int, list] = {}
    pos, vis = md.positions[::step], md.visible[::step]
    rate = md.rate_hz / step
    n = pos.shape[0]
    order = np.concatenate([np.arange(n), np.arange(n - 2, 0, -1)])  # ping-pong: no jump at the seams
    period_ns = int(round(1e9 / rate))
    prior_t = np.array([r[0] for r in rows], np.int64)
    src_t = np.asarray(md.stamps_ns[::step], np.int64)
    model, chamfer = load_models(body_model)
    # as the live launch files run it: lock upgrades in the worker process beside the estimates
    solver = WindowedSolver(model, replace(WindowedSolverConfig(), upgrade_in_background=True), up_axis, rate, chamfer)
    solver.wait_worker(120)
    total = int(round(minutes * 60 * rate))
    marks: dict = {}
    t0 = time.perf_counter()
    next_prior = 0

    gt_looped = gt_joints[order] if gt_joints is not None else None  # frame k's truth at k % len(order)

    def score(results):
        if gt_looped is not None:
            add_refined_errors(minute_err, results, gt_looped, rate)

    for k in range(total):
        j = order[k % len(order)]
        st = k * period_ns
        # the prior of the source frame, re-stamped on the long take's clock
        if rows and next_prior <= st:
            i = min(int(np.searchsorted(prior_t, src_t[j])), len(rows) - 1)
            r = rows[i]
            solver.add_prior(st, *r[1:])
            next_prior = st + int(round(1e9 / 30.0))
        score(solver.add_markers(st, pos[j], vis[j], frame_index=k))
        if k + 1 == int(round(60 * rate)) or k + 1 == total:
            pid = solver.worker_pid
            marks[f"{(k + 1) / rate / 60:.0f}min"] = {
                "peak_rss_mib": round(_rss_mib(), 1), "solver_memory": _proc_memory_mib(),
                "worker_memory": _proc_memory_mib(pid) if pid else {},
                "buffers": solver.buffer_sizes(), "wall_s": round(time.perf_counter() - t0, 1)}
        if k % 200 == 0:
            bar.set_postfix_str(f"long take {k / rate / 60:.1f}/{minutes:g} min")
    t_end = time.perf_counter()
    final = solver.flush()
    score(final)
    revised = sum(r.kind == "revised" for r in final)
    # the take's end: the last lock upgrade and the revision of the ring (up to revise_s of frames)
    marks["end"] = {"flush_s": round(time.perf_counter() - t_end, 1), "revised_frames": revised,
                    "upgrade_at_end_s": solver.stats.get("upgrade_at_end_s"), "revise_at_end_s": solver.stats.get("revise_at_end_s")}
    solver.close()
    refined_by_minute = {m + 1: round(1000.0 * float(np.mean(v)), 2) for m, v in sorted(minute_err.items())}
    return {"minutes": minutes, "rate_hz": rate, "frames": total, "marks": marks, "refined_mpjpe_by_minute": refined_by_minute,
            "stats": {k: v for k, v in solver.stats.items() if k != "bootstrap_seconds"}}


def _mean(rows, key):
    v = [r[key] for r in rows if isinstance(r.get(key), (int, float)) and np.isfinite(r[key])]
    return float(np.mean(v)) if v else float("nan")


def run(args) -> int:
    from tqdm import tqdm

    sessions = _sessions(args)
    bar = tqdm(total=len(sessions) + (0 if args.no_long_take else 1), desc="bench speed", unit="job", file=sys.stderr,
               disable=args.quiet)
    rows = []
    for s in sessions:
        rows.append(bench_session(s, not args.no_offline, bar))
        bar.update(1)
    long = None
    if not args.no_long_take:
        long = long_take(sessions[0], args.long_minutes, args.long_rate, bar)
        bar.update(1)
    bar.close()
    keys = ["steady_fps", "steady_fps_cpu", "realtime_factor", "bootstrap_s", "refined_mpjpe", "refined_mpjve", "estimate_mpjpe", "estimate_mpjve",
            "recording_mpjpe", "recording_mpjve", "offline_mpjpe", "offline_mpjve", "offline_s", "revise_at_end_s",
            "upgrade_at_end_s"]
    summary = {k: _mean(rows, k) for k in keys}
    summary["estimate_latency_p95_ms"] = _mean([r["estimate_latency_ms"] for r in rows], "p95")
    summary["estimate_latency_p99_ms"] = _mean([r["estimate_latency_ms"] for r in rows], "p99")
    summary["estimate_latency_max_ms"] = max((r["estimate_latency_ms"]["max"] for r in rows), default=float("nan"))
    summary["refined_latency_p95_ms"] = _mean([r["refined_latency_ms"] for r in rows], "p95")
    summary["refined_lag_ms"] = _mean([r["refined_latency_ms"] for r in rows], "lag")
    summary["queue_model_estimate_p95_ms"] = _mean([r["queue_model_ms"] for r in rows], "estimate_p95")
    summary["queue_model_refined_p95_minus_lag_ms"] = _mean([r["queue_model_ms"] for r in rows], "refined_p95_minus_lag")
    result = {"sessions": rows, "summary": summary, "long_take": long,
              "targets": {"fps": TARGET_FPS, "estimate_p95_ms": TARGET_P95_MS, "bootstrap_s": TARGET_BOOTSTRAP_S}}
    lines = ["session                         frames   fps fps/cpu  RTx  boot s  est p95 ms  ref p95 ms  "
             "MPJPE ref/est/off mm   MPJVE ref/est/off mm/s"]
    for r in rows:
        lines.append(f"{Path(r['session']).name[:30]:30s} {r['frames']:6d} {r['steady_fps']:6.1f} {r['steady_fps_cpu']:6.1f} {r['realtime_factor']:5.2f} "
                     f"{r['bootstrap_s']:6.1f} {r['estimate_latency_ms']['p95']:10.1f} {r['refined_latency_ms']['p95']:10.1f}  "
                     f"{r.get('refined_mpjpe', float('nan')):6.1f}/{r.get('estimate_mpjpe', float('nan')):5.1f}/"
                     f"{r.get('offline_mpjpe', float('nan')):5.1f}        "
                     f"{r.get('refined_mpjve', float('nan')):6.1f}/{r.get('estimate_mpjve', float('nan')):6.1f}/"
                     f"{r.get('offline_mpjve', float('nan')):6.1f}")
    s = summary
    lines.append(f"mean: {s['steady_fps']:.1f} frames/s wall, {s['steady_fps_cpu']:.1f} per CPU-second "
                 f"(real-time factor {s['realtime_factor']:.2f}; target >= {TARGET_FPS:g}), "
                 f"estimate latency p95 {s['estimate_latency_p95_ms']:.1f} ms (target <= {TARGET_P95_MS:g}; p99 "
                 f"{s['estimate_latency_p99_ms']:.1f}, max {s['estimate_latency_max_ms']:.1f}), "
                 f"refined latency p95 {s['refined_latency_p95_ms']:.1f} ms = lag+hop {s['refined_lag_ms']:.1f} ms + "
                 f"{s['refined_latency_p95_ms'] - s['refined_lag_ms']:.1f} ms, bootstrap {s['bootstrap_s']:.1f} s "
                 f"(target <= {TARGET_BOOTSTRAP_S:g})")
    lines.append(f"queue model (the measured per-call times served one at a time at the capture rate, no waits for a "
                 f"core): estimate latency p95 {s['queue_model_estimate_p95_ms']:.1f} ms, refined latency p95 = lag+hop + "
                 f"{s['queue_model_refined_p95_minus_lag_ms']:.1f} ms")
    lines.append(f"accuracy: refined MPJPE {s['refined_mpjpe']:.1f} mm / MPJVE {s['refined_mpjve']:.1f} mm/s; estimate "
                 f"{s['estimate_mpjpe']:.1f} / {s['estimate_mpjve']:.1f}; offline {s['offline_mpjpe']:.1f} / {s['offline_mpjve']:.1f} "
                 f"(offline solve {s['offline_s']:.1f} s per session); recording (revised frames - after a lock upgrade and "
                 f"at the take's end, {sum(r.get('revised_frames', 0) for r in rows)} frames, else refined) {s['recording_mpjpe']:.1f} / "
                 f"{s['recording_mpjve']:.1f}; at the take's end the lock upgrade took {s['upgrade_at_end_s']:.1f} s and the "
                 f"revision {s['revise_at_end_s']:.1f} s per session")
    ups = [(Path(r["session"]).name[:16], r["lock_upgrades_started"], r["lock_upgrades"], r["lock_upgrade_s"]) for r in rows]
    lines.append("bootstrap starts (Stage-5 marker fit, mm; * = locked): " + "; ".join(
        f"{Path(r['session']).name[:16]} " + " / ".join(("-" if f is None else f"{f:.2f}") + ("*" if i == r["bootstrap_start_chosen"] else "")
                                                       for i, f in enumerate(r["bootstrap_start_fits_mm"] or []))
        for r in rows))
    lines.append("lock upgrades (worker process; one still running when the take ends is dropped, the take's end runs its own): " + "; ".join(
        f"{n} {k0} started, {k} adopted or refused in {', '.join(f'{x:.1f}' for x in t) or '-'} s" for n, k0, k, t in ups))
    if long:
        for name, m in long["marks"].items():
            if name == "end":
                lines.append(f"long take end (flush {m['flush_s']:.1f} s): the last lock upgrade {m['upgrade_at_end_s'] or 0:.1f} s, "
                             f"the ring's revision {m['revise_at_end_s'] or 0:.1f} s, {m['revised_frames']} frames revised")
                continue
            mem = "; ".join(f"{who} RSS {d['rss_mib']:.1f} MiB (peak {d['peak_mib']:.1f})"
                            for who, d in (("solver", m.get("solver_memory", {})), ("worker", m.get("worker_memory", {}))) if d)
            lines.append(f"long take {name}: {mem or 'peak RSS %.1f MiB' % m['peak_rss_mib']}, buffers {m['buffers']}, wall {m['wall_s']:.0f} s")
    if long and long.get("refined_mpjpe_by_minute"):
        by = long["refined_mpjpe_by_minute"]
        off = rows[0].get("offline_mpjpe", float("nan"))
        lines.append("long take live fixed-lag refined MPJPE by minute (mm; frames fed as fast as the solver takes them, so "
                     "lock upgrades land later in the take than live): " + ", ".join(f"{m}: {v:.1f}" for m, v in by.items())
                     + f" (the offline solve of its source session: {off:.1f})")
    text = "\n".join(lines)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=float))
    return 0


def register_bench(subparsers) -> None:
    p = subparsers.add_parser("speed", help="near-online windowed solver vs offline: frames/s, latency, bootstrap, accuracy, memory",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", action="append", metavar="DIR", help="session directory (repeatable; default: generated sessions)")
    p.add_argument("--sessions", type=int, default=2, help="generated sessions (walk, jump, arms, ...; default 2)")
    p.add_argument("--rate", type=float, default=120.0, help="marker rate of generated sessions (default 120 Hz)")
    p.add_argument("--duration", type=float, default=8.0, help="seconds per generated session (default 8)")
    p.add_argument("--markers", type=int, default=40, help="markers per generated session (default 40)")
    p.add_argument("--cache", metavar="DIR", help="session cache (default: the bench accuracy cache)")
    p.add_argument("--no-offline", action="store_true", help="skip the offline solver (no side-by-side accuracy)")
    p.add_argument("--no-long-take", action="store_true", help="skip the long-take memory check")
    p.add_argument("--long-minutes", type=float, default=10.0, help="length of the long take (default 10 minutes)")
    p.add_argument("--long-rate", type=float, default=30.0, help="marker rate of the long take (default 30 Hz)")
    p.add_argument("--json", metavar="FILE", help="write all results as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_handler)


def _handler(args) -> int:
    if args.sessions < 1 or args.rate <= 0 or args.duration <= 0 or args.markers < 1 or args.long_minutes <= 0 or args.long_rate <= 0:
        raise UserError("--sessions, --rate, --duration, --markers, --long-minutes and --long-rate must be positive")
    return run(args)
