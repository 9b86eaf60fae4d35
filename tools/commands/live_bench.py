"""``uuomocap bench live``: a session streamed as a live OptiTrack source, its video as the camera.

What a studio runs, end to end on this machine, with the session's ground truth to score it:
``uuomocap launch live_natnet solve:=true label:=true video:=SESSION/video.mp4`` is started and
left to come up (``--lead`` seconds: a studio's graph is up before the take), then ``uuomocap natnet
serve SESSION/markers.c3d`` streams the markers in real time over NatNet (UDP, Motive's protocol,
Motive's clock) while the video plays as a camera started with the marker stream, stamped on the
marker clock by the video node's clock bridge.  The recording's solved body (the recorder's npz
export) is scored against gt.npz, frames matched by their stamps; printed too: the bootstrap's
seconds, the video priors that arrived (and how many found a person), the names on markers/named.
Real time: a 20 s take takes ~1.5 min beside the lead.
"""

from __future__ import annotations

import argparse
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from uuomocap.commands import UserError, emit_bench


def register_bench(subparsers) -> None:
    p = subparsers.add_parser("live", help="a session through live_natnet in real time (NatNet stream + video as a camera), scored",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", required=True, metavar="DIR", help="session with markers.c3d, video.mp4 and gt.npz "
                   "(`uuomocap sample make DIR` writes one)")
    p.add_argument("--lead", type=float, default=25.0, help="seconds the graph runs before the take starts (default 25)")
    p.add_argument("--layout", default="segments", help="the namer's layout: segments | plug-in-gait | template .npz")
    p.add_argument("--keep", metavar="DIR", help="keep the recording and node logs in this directory")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE", help="write results as JSON to FILE (or stdout)")
    p.set_defaults(func=run)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def score(npz: Path, gt_path: Path, rate_hz: float) -> dict:
    """The recording's solve against gt.npz: frame i of the stream is stamped i / rate on the server's clock."""
    from uuomocap.protocol.session import read_npz
    from uuomocap.solver_core.metrics import mpjpe, mpjve

    pred, gt = read_npz(npz), read_npz(gt_path)
    idx = np.round(np.asarray(pred["stamps_ns"], np.float64) / 1e9 * rate_hz).astype(np.int64)
    gj = np.asarray(gt["joints"], np.float64)
    keep = (idx >= 0) & (idx < len(gj))
    pj = np.asarray(pred["joints"], np.float64)[keep]
    return {"frames_solved": int(keep.sum()), "frames_in_take": int(len(gj)), "mpjpe_mm": mpjpe(pj, gj[idx[keep]]),
            "mpjve_mm_s": mpjve(pj, gj[idx[keep]], rate_hz) if np.all(np.diff(idx[keep]) == 1) else float("nan")}


def run(args) -> int:
    from tqdm import tqdm

    from uuomocap.protocol.messages import BodyPrior, MarkerFrame
    from uuomocap.protocol.recording import iter_recording
    from uuomocap.protocol.session import SessionError, load_session

    session = Path(args.session)
    try:
        s = load_session(session, load_prior=False, load_gt=False)
    except SessionError as exc:
        raise UserError(str(exc)) from None
    video = session / "video.mp4"
    for need in (session / "markers.c3d", video, session / "gt.npz"):
        if not need.is_file():
            raise UserError(f"{session}: {need.name} is missing (bench live streams markers.c3d with video.mp4 and scores against gt.npz)")
    if not args.lead >= 0:
        raise UserError("--lead must be >= 0")
    md = s.markers
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="uuomocap-bench-live-"))
    work.mkdir(parents=True, exist_ok=True)
    out, logs, port = work / "live.mcap", work / "logs", _free_port()
    frames = md.n_frames - 5  # the graph ends on the source's last frame; the last few may not reach it
    graph_timeout = args.lead + 4 * md.duration_s + 240
    cli = [sys.executable, "-m", "uuomocap.cli"]
    launcher = subprocess.Popen([*cli, "launch", "--log-dir", str(logs), "--timeout", str(int(graph_timeout)), "live_natnet",
                                 f"command_port:={port}", "solve:=true", "label:=true", f"layout:={args.layout}", f"video:={video}",
                                 f"max_frames:={frames}", f"up_axis:={md.up_axis}", f"out:={out}"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    try:
        for _ in tqdm(range(int(args.lead * 10)), desc="graph coming up", unit="ds", leave=False, mininterval=1.0):
            time.sleep(0.1)
            if launcher.poll() is not None:
                raise UserError(f"the graph ended before the take (exit code {launcher.returncode}); node logs in {logs}")
        t0 = time.monotonic()
        subprocess.run([*cli, "natnet", "serve", str(session / "markers.c3d"), "--command-port", str(port), "--wait-client", "60"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL, check=False)
        code = launcher.wait(timeout=graph_timeout)
    except (KeyboardInterrupt, subprocess.TimeoutExpired):
        launcher.terminate()
        launcher.wait(30)
        raise
    wall = time.monotonic() - t0
    npz = out.with_suffix(".npz")
    if not npz.is_file():
        raise UserError(f"the graph recorded no solved frame (exit code {code}); node logs in {logs}")
    res = {"session": str(session), "rate_hz": md.rate_hz, "take_s": md.duration_s, "markers": md.n_markers, "lead_s": args.lead,
           "graph_exit_code": code, "wall_s_from_take_start": round(wall, 1), **score(npz, session / "gt.npz", md.rate_hz)}
    solver_log = (logs / "solver.log").read_text(errors="replace") if (logs / "solver.log").is_file() else ""
    res["bootstrap_s"] = [float(x) for x in re.findall(r"bootstrap done in ([0-9.]+) s", solver_log)]
    priors = [m for m in (r.decode().message for r in iter_recording(out, topics=["body/prior"])) if isinstance(m, BodyPrior)]
    res["priors"], res["priors_with_person"] = len(priors), sum(bool(p.valid) for p in priors)
    named = [m for m in (r.decode().message for r in iter_recording(out, topics=["markers/named"])) if isinstance(m, MarkerFrame)]
    res["named_frames"] = sum(1 for m in named if any(m.labels))
    res["names_last_frame"] = sum(1 for n in (named[-1].labels if named else []) if n)
    res["work_dir"] = str(work)
    text = (f"bench live: {md.duration_s:.1f} s, {md.rate_hz:g} Hz, {md.n_markers} markers over NatNet + the video as a camera "
            f"(graph up {args.lead:g} s before the take), exit code {code}\n"
            f"solved {res['frames_solved']} of {res['frames_in_take']} frames: MPJPE {res['mpjpe_mm']:.1f} mm, "
            f"MPJVE {res['mpjve_mm_s']:.1f} mm/s against gt.npz\n"
            f"bootstrap {' / '.join(f'{b:.1f}' for b in res['bootstrap_s']) or '-'} s; video priors {res['priors']} "
            f"({res['priors_with_person']} with a person); markers/named: {res['named_frames']} frames named, "
            f"{res['names_last_frame']} names on the last\n(recording and node logs: {work})")
    emit_bench(args, res, text)
    return 0 if code == 0 else 1
