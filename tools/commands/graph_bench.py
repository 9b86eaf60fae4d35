"""``uuomocap bench graph``: real-time replay through the real graph; completeness, drops, latency.

A 120 Hz, 10 s capture is replayed in real time through a launched graph
(separate processes, broker, recorder). The recording is then checked: every
frame recorded, sequence numbers without gaps. Latency:
  with a solver (``--session DIR`` and the ``solver`` plugin installed):
      marker frame published -> solved frame published (same capture stamp; the
      first answer per frame, i.e. the 'estimate', and the 'refined' one);
  otherwise: marker frame published -> received by the recorder.
Both ends are CLOCK_MONOTONIC on this machine.  With a solver the first frames wait for its
bootstrap (the offline solver on the first seconds) and the backlog behind it, so the solver's
latency is also split at the point it caught up: printed are the time of the first solved frame,
when the solver caught up, and the steady-state latency of every frame from then on.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, emit_bench


def register_bench(subparsers) -> None:
    p = subparsers.add_parser("graph", help="real-time replay through the graph: drops and latency p50/p95/p99",
                              description=__doc__, formatter_class=__import__("argparse").RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0, help="capture length (default 10)")
    p.add_argument("--rate", type=float, default=120.0, help="capture rate in Hz (default 120)")
    p.add_argument("--markers", type=int, default=41, help="markers per frame of the synthetic capture")
    p.add_argument("--session", help="session directory: run replay_session (needs the solver plugins)")
    p.add_argument("--keep", help="keep the capture and recording in this directory")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE", help="write results as JSON to FILE (or stdout)")
    p.set_defaults(func=run)


def synthetic_capture(path: Path, seconds: float, rate: float, n_markers: int, seed: int = 0) -> int:
    """Smooth marker trajectories around a walking-speed drift, ~2% samples missing."""
    from uuomocap.protocol.markerio import write_c3d

    rng = np.random.default_rng(seed)
    T = int(round(seconds * rate))
    t = np.arange(T)[:, None, None] / rate
    base = rng.uniform([-0.3, -0.2, 0.1], [0.3, 0.2, 1.8], (1, n_markers, 3))
    phase = rng.uniform(0, 2 * np.pi, (1, n_markers, 3))
    pos = base + 0.05 * np.sin(2 * np.pi * 1.2 * t + phase) + np.array([1.0, 0, 0]) * t
    pos[rng.random((T, n_markers)) < 0.02] = np.nan
    write_c3d(path, pos, rate)
    return T


def _percentiles(ms: np.ndarray) -> dict:
    if not len(ms):
        return {}
    return {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max()), "n": int(len(ms))}


def steady_state(marker_pt: dict[int, int], answer_pt: dict[int, int]) -> dict:
    """Split the solver's latency at the point it caught up after its bootstrap.

    marker_pt / answer_pt: capture stamp -> publish time of the marker frame / of its first solved
    frame.  The first frames wait for the bootstrap (the offline solver on the first seconds) and
    the backlog behind it; steady state starts at the first frame published after every earlier
    frame had been answered, and includes every later frame (later stalls count)."""
    stamps = sorted(s for s in marker_pt if s in answer_pt)
    if not stamps:
        return {}
    mp = np.array([marker_pt[s] for s in stamps], dtype=np.int64)
    ap = np.array([answer_pt[s] for s in stamps], dtype=np.int64)
    answered_before = np.maximum.accumulate(ap)  # [k]: every frame up to k answered by then
    caught = np.flatnonzero(mp[1:] >= answered_before[:-1])
    out = {"first_answer_after_s": float((ap.min() - mp[0]) / 1e9)}
    if not len(caught):
        out.update(caught_up_at_s=None, steady_frames=0, latency_steady_ms={})
        return out
    k = int(caught[0]) + 1
    out.update(caught_up_at_s=float((mp[k] - mp[0]) / 1e9), steady_frames=int(len(stamps) - k),
               latency_steady_ms=_percentiles((ap[k:] - mp[k:]) / 1e6))
    return out


def analyse(mcap: Path, expected_frames: int) -> dict:
    from uuomocap.protocol.recording import RecordingInfo, iter_recording

    info = RecordingInfo(str(mcap))
    marker_pt: dict[int, int] = {}
    seqs, recv_lat, solved = [], [], {"estimate": [], "refined": []}
    first_answer: dict[int, int] = {}
    for rec in iter_recording(mcap, info=info):
        env = rec.decode()
        if env.type == "MarkerFrame":
            seqs.append(env.seq)
            marker_pt[env.stamp_ns] = env.publish_ns
            recv_lat.append((rec.log_time_ns - rec.publish_time_ns) / 1e6)
        elif env.type == "SolvedFrame":
            solved.setdefault(env.message.kind, []).append((env.stamp_ns, env.publish_ns))
            first_answer.setdefault(env.stamp_ns, env.publish_ns)
    seqs_arr = np.array(sorted(seqs))
    gaps = int(np.sum(np.diff(seqs_arr) - 1)) if len(seqs_arr) > 1 else 0
    out = {
        "frames_expected": expected_frames,
        "frames_recorded": len(seqs),
        "drops": gaps + (int(seqs_arr[0]) if len(seqs_arr) else 0),
        "duplicates": len(seqs) - len(set(seqs)),
        "recording_truncated": info.truncated,
        "latency_marker_to_recorder_ms": _percentiles(np.array(recv_lat)),
    }
    if first_answer:
        lat = [(pt - marker_pt[s]) / 1e6 for s, pt in first_answer.items() if s in marker_pt]
        out["latency_marker_to_solved_ms"] = _percentiles(np.array(lat))
        out.update(steady_state(marker_pt, first_answer))
        for kind, rows in solved.items():
            lat = [(pt - marker_pt[s]) / 1e6 for s, pt in rows if s in marker_pt]
            out[f"latency_marker_to_{kind}_ms"] = _percentiles(np.array(lat))
        out["solved_frames"] = len(first_answer)
    return out


def steady_text(res: dict) -> str:
    if "first_answer_after_s" not in res:
        return ""
    text = f"solver: first solved frame {res['first_answer_after_s']:.1f} s after the first marker frame (bootstrap); "
    if res["caught_up_at_s"] is None:
        return text + "never caught up with the replay (no steady state in this capture)\n"
    lat = res["latency_steady_ms"]
    return text + (f"caught up at {res['caught_up_at_s']:.1f} s\n"
                   f"steady-state latency ({res['steady_frames']} frames from then on): p50 {lat['p50']:.2f} ms  "
                   f"p95 {lat['p95']:.2f} ms  p99 {lat['p99']:.2f} ms  max {lat['max']:.2f} ms\n")


def run(args) -> int:
    from tqdm import tqdm

    from uuomocap.launcher import LaunchError, Launcher, load_launch, validate
    from uuomocap.nodes.base import discover_plugins

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="uuomocap-bench-graph-"))
    work.mkdir(parents=True, exist_ok=True)
    out = work / "bench.mcap"
    if args.session:
        missing = [p for p in ("segmenter", "solver") if p not in discover_plugins()]
        if missing:
            raise UserError(f"--session needs the node plugins {', '.join(missing)}, which are not installed")
        session = Path(args.session)
        from uuomocap.protocol.markerio import read_markers

        md = read_markers(session / "markers.c3d")
        frames, seconds, rate = md.n_frames, md.duration_s, md.rate_hz
        spec = load_launch("replay_session", {"session": str(session), "out": str(out)})
        mode = "marker published -> solved published"
    else:
        frames = synthetic_capture(work / "capture.c3d", args.seconds, args.rate, args.markers)
        seconds, rate = args.seconds, args.rate
        spec = load_launch("record_markers", {"markers": str(work / "capture.c3d"), "out": str(out), "topics": ["markers/raw"]})
        mode = "marker published -> recorder received (no solver in this graph)"
    try:
        graph = validate(spec)
    except LaunchError as exc:
        raise UserError(str(exc)) from None
    launcher = Launcher(graph, log_dir=work / "logs", quiet=True)
    started = time.monotonic()
    bar = tqdm(total=round(seconds, 1), unit="s", desc=f"{rate:g} Hz replay", leave=False, mininterval=0.5)

    def tick(_):
        done = min(round(time.monotonic() - started, 1), bar.total)
        if done > bar.n:
            bar.update(round(done - bar.n, 1))  # update() honours tqdm's refresh interval

    launcher.start()
    code = launcher.supervise(timeout_s=seconds * 3 + 60, on_tick=tick)
    bar.close()
    if not out.is_file():
        raise UserError(f"the graph wrote no recording (exit code {code}); node logs in {work / 'logs'}")
    res = {"mode": mode, "rate_hz": rate, "seconds": seconds, "graph_exit_code": code, "wall_s": time.monotonic() - started,
           **analyse(out, frames), "work_dir": str(work)}
    ok = code == 0 and res["frames_recorded"] == frames and res["drops"] == 0
    res["ok"] = ok
    key = "latency_marker_to_solved_ms" if "latency_marker_to_solved_ms" in res else "latency_marker_to_recorder_ms"
    lat = res[key]
    text = (f"bench graph: {frames} frames at {rate:g} Hz in real time, {res['frames_recorded']} recorded, "
            f"{res['drops']} drops, {res['duplicates']} duplicates\n"
            f"latency ({mode}): p50 {lat.get('p50', float('nan')):.2f} ms  p95 {lat.get('p95', float('nan')):.2f} ms  "
            f"p99 {lat.get('p99', float('nan')):.2f} ms  max {lat.get('max', float('nan')):.2f} ms\n"
            + steady_text(res) +
            f"{'OK' if ok else 'FAILED'}  (recording and node logs: {work})")
    emit_bench(args, res, text)
    return 0 if ok else 1
