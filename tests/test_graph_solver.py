"""The solver and segmenter plugins in the real graph: a generated session replayed in lockstep
through replay -> prior -> segmenter -> solver -> recorder, twice, gives byte-identical solved
output; the exported npz has a refined frame per marker frame and evaluates against gt.npz."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from uuomocap.nodes.base import discover_plugins
from uuomocap.protocol.messages import MarkerFrame
from uuomocap.protocol.recording import iter_recording

DEADLINE = 240.0


def start_graph(tmp_path: Path, launch: str, session: Path, out: Path, tag: str, *args: str) -> tuple[subprocess.Popen, Path]:
    """The launcher on ``launch`` (bootstrap 1.5 s, more ``key:=value`` args) in its own session -> (process, log dir)."""
    logs = tmp_path / f"logs-{tag}"
    logs.mkdir()
    with open(logs / "launcher.log", "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "uuomocap.launcher", launch, f"session:={session}", f"out:={out}",
                                 "bootstrap_s:=1.5", *args, "--log-dir", str(logs)], stdout=log, stderr=log, stdin=subprocess.DEVNULL,
                                start_new_session=True)
    return proc, logs


def run_graph(tmp_path: Path, session: Path, out: Path, tag: str, *args: str) -> int:
    proc, logs = start_graph(tmp_path, "offline_solve", session, out, tag, *args)
    try:
        code = proc.wait(DEADLINE)
        if code != 0:  # which node ended how (the launcher says) and every node's last lines
            tails = {f.name: f.read_text(errors="replace").splitlines()[-8:] for f in sorted(logs.glob("*.log"))}
            print(f"graph exited with {code}:\n" + "\n".join(f"--- {k}\n" + "\n".join(v) for k, v in tails.items()))
        return code
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        raise AssertionError(f"graph did not finish in {DEADLINE}s; logs in {logs}")


def raw_frames(path: Path) -> list:
    return [m for m in (rec.decode().message for rec in iter_recording(path, topics=["markers/raw"])) if isinstance(m, MarkerFrame)]


def solved_content(path: Path) -> list:
    """What must be identical between two lockstep runs (not publish times or instance ids): each
    topic's messages in publish order.  How the recorder interleaves the solver's and the
    segmenter's topics depends on which process is ready first, so the topics are compared apart."""
    out = []
    for rec in iter_recording(path, topics=["body/solved", "markers/labels"]):
        e = rec.decode()
        m = e.message
        out.append((e.topic, e.type, e.seq, e.stamp_ns, sorted(m.scalars().items()),
                    [(k, a.dtype.str, a.shape, a.tobytes()) for k, a in m.arrays().items()]))
    return sorted(out, key=lambda c: (c[0], c[2]))  # by topic, then the publisher's sequence number


@pytest.mark.slow
def test_lockstep_replay_through_the_solver_is_reproducible(tmp_path):
    if not {"solver", "segmenter"} <= set(discover_plugins()):
        pytest.skip("solver/segmenter plugins are not installed (pip install -e .)")
    from uuomocap.commands.eval import evaluate_paths
    from uuomocap.synth import SampleConfig, make_session

    session = tmp_path / "s"
    make_session(session, SampleConfig(motion="walk", rate_hz=30.0, duration_s=3.0, n_markers=40, seed=0, video=False))
    outs = [tmp_path / f"run{i}.mcap" for i in range(2)]
    for i, out in enumerate(outs):
        assert run_graph(tmp_path, session, out, f"r{i}") == 0
    a, b = (solved_content(o) for o in outs)
    kinds = [c[4] for c in a if c[0] == "body/solved"]
    assert a == b and len(a) > 0
    frames = 90
    n_est = sum(1 for c in a if c[0] == "body/solved" and ("kind", "estimate") in c[4])
    n_ref = sum(1 for c in a if c[0] == "body/solved" and ("kind", "refined") in c[4])
    assert n_est == frames and n_ref == frames, (n_est, n_ref, len(kinds))
    assert any(c[0] == "markers/labels" for c in a)  # the segmenter labelled the markers
    npz = [o.with_suffix(".npz") for o in outs]
    x, y = np.load(npz[0]), np.load(npz[1])
    assert sorted(x.files) == sorted(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)
    # the take's end revises every frame once more (WindowedSolverConfig.revise_at_end): the recording keeps those.
    # A lock upgrade adopted mid-take revises the frames before it too (session 33's install adopted one here:
    # 70 + 90 revised results), so every frame is revised at least once and the last revision covers all
    revised = [dict(c[4])["frame_index"] for c in a if c[0] == "body/solved" and ("kind", "revised") in c[4]]
    estimated = [dict(c[4])["frame_index"] for c in a if c[0] == "body/solved" and ("kind", "estimate") in c[4]]
    assert sorted(set(revised)) == sorted(estimated) and sorted(revised[-frames:]) == sorted(estimated), (revised, estimated)
    assert (x["frame_kind"] == "revised").all() and x["poses"].shape == (frames, 72)
    metrics = evaluate_paths(npz[0], session / "gt.npz", session / "markers.c3d")
    assert metrics["mpjpe"] < 60.0, metrics


@pytest.mark.slow
def test_a_live_stop_keeps_every_estimated_frame_refined(tmp_path):
    """Ctrl-C on a running take (SIGINT to the launcher, which stops the graph in data-flow order):
    the solver handles what is still queued and flushes the frames inside its fixed lag, so the
    recording holds a refined frame for every frame it estimated (before: the last lag frames and
    any backlog were dropped)."""
    import time

    if "solver" not in set(discover_plugins()):
        pytest.skip("solver plugin is not installed (pip install -e .)")
    from uuomocap.synth import SampleConfig, make_session

    session = tmp_path / "s"
    make_session(session, SampleConfig(motion="walk", rate_hz=30.0, duration_s=60.0, n_markers=40, seed=0, video=False))
    out = tmp_path / "live.mcap"
    proc, logs = start_graph(tmp_path, "replay_session", session, out, "live", "label:=true")
    try:
        deadline = time.monotonic() + DEADLINE
        solver_log = logs / "solver.log"
        while not (solver_log.exists() and "bootstrap done" in solver_log.read_text(errors="replace")):
            assert proc.poll() is None, f"graph ended before the solver bootstrapped; logs in {logs}"
            assert time.monotonic() < deadline, f"no bootstrap in {DEADLINE}s; logs in {logs}"
            time.sleep(0.2)
        time.sleep(3.0)  # the take goes on (60 s of markers: still streaming, whatever the bootstrap took)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert code == 0, (logs / "launcher.log").read_text(errors="replace")[-2000:]
    # (a lock upgrade that landed before the stop also re-publishes earlier frames as 'revised')
    kinds: dict[str, set[int]] = {"estimate": set(), "refined": set(), "revised": set()}
    for rec in iter_recording(out, topics=["body/solved"]):
        m = rec.decode().message
        kinds[m.kind].add(int(m.frame_index))
    assert 45 <= len(kinds["estimate"]) < 1800, len(kinds["estimate"])  # stopped mid-take, after the bootstrap
    assert kinds["refined"] == kinds["estimate"], sorted(kinds["estimate"] - kinds["refined"])[:20]
    assert kinds["revised"] <= kinds["refined"]
    exported = np.load(out.with_suffix(".npz"))
    assert len(exported["frame_kind"]) == len(kinds["estimate"]) and np.isin(exported["frame_kind"], ("refined", "revised")).all()
    assert (exported["frame_kind"] == "revised").sum() == len(kinds["revised"])
    # the namer (label:=true) drained too: every recorded marker frame is on markers/named, and the
    # frames after the lock carry a name per marker, each once
    raw = [rec.decode().message for rec in iter_recording(out, topics=["markers/raw"])]
    named = [rec.decode().message for rec in iter_recording(out, topics=["markers/named"])]
    raw, named = ([m for m in ms if isinstance(m, MarkerFrame)] for ms in (raw, named))
    assert [m.stamp_ns for m in named] == [m.stamp_ns for m in raw]
    last = named[-1].labels
    assert len(last) == 40 and all(last) and len(set(last)) == 40, last
    assert np.array_equal(named[-1].positions, raw[-1].positions)


@pytest.mark.slow
def test_the_namer_names_a_plug_in_gait_take_in_the_graph(tmp_path):
    """markers/named in a lockstep replay (launch label:=true layout:=plug-in-gait): every frame goes
    out with its solved answer, the bootstrap's frames too, with the Plug-in Gait names, which are the
    session's true names; the recording reads back as a labelled marker file."""
    if not {"solver", "namer"} <= set(discover_plugins()):
        pytest.skip("solver/namer plugins are not installed (pip install -e .)")
    from uuomocap.protocol.recording import read_markers_mcap
    from uuomocap.protocol.session import read_npz
    from uuomocap.synth import SampleConfig, make_session

    session = tmp_path / "pig"
    make_session(session, SampleConfig(motion="walk", rate_hz=30.0, duration_s=3.0, n_markers=39, seed=3, video=False,
                                       layout="structured"))
    out = tmp_path / "run.mcap"
    assert run_graph(tmp_path, session, out, "pig", "label:=true", "layout:=plug-in-gait") == 0
    truth = [str(n) for n in read_npz(session / "gt.npz")["marker_names"]]
    named = [m for m in (rec.decode().message for rec in iter_recording(out, topics=["markers/named"])) if isinstance(m, MarkerFrame)]
    assert [m.frame_index for m in named] == [m.frame_index for m in raw_frames(out)] and len(named) == 90
    assert all(len(m.labels) == 39 and all(m.labels) for m in named)  # the bootstrap's 45 frames named with the lock
    right = sum(a == b for a, b in zip(named[-1].labels, truth))
    assert right >= 35, list(zip(named[-1].labels, truth))
    md = read_markers_mcap(out, topic="markers/named")
    assert md.labelled and md.labels == named[-1].labels and md.n_frames == 90
