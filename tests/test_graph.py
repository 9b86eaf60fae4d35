"""The streaming graph end to end: real processes, sockets, launch files, recordings.

Every wait polls with a generous deadline (the machine is shared and small);
no sleep is an assertion.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from uuomocap.launcher import LaunchError, flow_levels, load_launch, validate
from uuomocap.nodes.base import Runtime, discover_plugins
from uuomocap.nodes.marker_replay import MarkerReplay
from uuomocap.nodes.recorder import Recorder
from uuomocap.protocol.envelope import encode
from uuomocap.protocol.markerio import read_markers, write_c3d
from uuomocap.protocol.messages import MarkerFrame, SolvedFrame
from uuomocap.protocol.prior_file import write_prior_npz
from uuomocap.protocol.recording import RecordingError, RecordingWriter, iter_recording, recording_info
from uuomocap.protocol.transport import BrokerThread, Endpoints, Publisher, Subscriber, runtime_root

DEADLINE = 90.0


def write_capture(path: Path, frames: int, rate: float = 120.0, markers: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] / rate
    pos = rng.uniform(-0.5, 0.5, (1, markers, 3)) + 0.05 * np.sin(2 * np.pi * t + rng.uniform(0, 6, (1, markers, 3)))
    pos[rng.random((frames, markers)) < 0.05] = np.nan
    write_c3d(path, pos, rate)
    return pos


def write_yaml(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def start_launch(tmp_path: Path, file, *args: str, tag: str = "g") -> subprocess.Popen:
    logs = tmp_path / f"logs-{tag}"
    logs.mkdir(exist_ok=True)
    out = open(logs / "launcher.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "uuomocap.launcher", str(file), *args, "--log-dir", str(logs)],
                            stdout=out, stderr=out, stdin=subprocess.DEVNULL, start_new_session=True)
    out.close()
    proc.logs = logs  # type: ignore[attr-defined]
    return proc


def finish(proc: subprocess.Popen, timeout: float = DEADLINE) -> int:
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        raise AssertionError(f"graph did not finish in {timeout}s; logs: {_logs(proc)}")


def _logs(proc) -> str:
    return "\n".join(f"== {f.name}\n{f.read_text()[-3000:]}" for f in sorted(proc.logs.glob("*.log")))


def poll(predicate, what: str, timeout: float = DEADLINE, every: float = 0.1):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = predicate()
        if value:
            return value
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")


def graph_json(proc: subprocess.Popen, name: str, nodes: int) -> dict:
    path = runtime_root() / f"{name}-{proc.pid}" / "graph.json"

    def ready():
        try:
            info = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        pids = [n["pid"] for n in info["nodes"]]
        return info if len(pids) == nodes and all(pids) and info["broker_pid"] else None

    return poll(ready, f"{path}")


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def group_members(pgid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] not in ("Z", "X"):
                out.append(int(d.name))
    return out


def recorded(path: Path, topic: str | None = None) -> list:
    try:
        return [r.decode() for r in iter_recording(path, topics=[topic] if topic else None)]
    except RecordingError:
        return []


def content(envs) -> list:
    """What must be identical between two lockstep runs (not publish times or instance ids)."""
    out = []
    for e in envs:
        m = e.message
        out.append((e.topic, e.type, e.seq, e.stamp_ns, sorted(m.scalars().items()),
                    [(k, a.dtype.str, a.shape, a.tobytes()) for k, a in m.arrays().items()]))
    return out


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------


def test_launch_validation_reports_every_problem(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 24)

    def problems(doc: dict, **args) -> str:
        with pytest.raises(LaunchError) as exc:
            validate(load_launch(write_yaml(tmp_path / "g.yaml", doc), args))
        return str(exc.value)

    replay = {"name": "replay", "plugin": "marker_replay", "params": {"file": str(cap)}}
    text = problems({"nodes": [
        replay,
        {"name": "x", "plugin": "no_such_plugin"},
        {"name": "rec", "plugin": "recorder", "params": {"out": "a.mcap", "chunk_kib": "big"}},
        {"name": "rec2", "plugin": "recorder", "params": {"out": "b.mcap", "colour": 1}},
        {"name": "relay", "plugin": "relay", "params": {"input": "markers/labels", "output": "x/y"}},
    ]})
    assert "plugin 'no_such_plugin' is not installed" in text and "marker_replay" in text
    assert "parameter 'chunk_kib' must be int" in text
    assert "unknown parameter 'colour'" in text
    assert "subscribes to 'markers/labels' (port input) but no node publishes it" in text

    assert "duplicate node name" in problems({"nodes": [replay, replay]})
    assert "no such marker file" in problems({"nodes": [{**replay, "params": {"file": "/nope.c3d"}}]})
    assert "ack_from names 'ghost'" in problems({"nodes": [{**replay, "params": {"file": str(cap), "ack_from": ["ghost"]}}]})
    deaf = {"name": "rec", "plugin": "recorder", "params": {"out": "a.mcap", "topics": ["other/topic"]}}
    assert "'rec' does not subscribe to any of its topics (markers/raw), so it never acknowledges" in problems(
        {"nodes": [{**replay, "params": {"file": str(cap), "ack_from": ["rec"]}}, deaf], "external_topics": ["other/topic"]})
    doc = {"args": {"m": {"help": "markers"}}, "nodes": [{**replay, "params": {"file": "$(arg m)"}}]}
    assert "argument 'm' is required (markers)" in problems(doc)
    assert "unknown argument 'speed'" in problems(doc, m=str(cap), speed=2)
    assert "$(arg q) names no declared argument" in problems({"nodes": [{**replay, "params": {"file": "$(arg q)"}}]})
    assert "respawn policy must be one of" in problems({"nodes": [{**replay, "respawn": "sometimes"}]})
    assert "nice must be an integer 0-19" in problems({"nodes": [{**replay, "nice": 25}]})

    # endpoint collisions: a tcp port someone holds, an ipc dir with a live broker
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        text = problems({"transport": {"kind": "tcp", "frontend_port": port, "backend_port": port}, "nodes": [replay]})
        assert "frontend and backend are the same" in text and "cannot be bound" in text
    broker = BrokerThread(Endpoints.ipc(tmp_path))
    try:
        assert "in use by another running graph" in problems({"transport": {"kind": "ipc", "dir": str(tmp_path)}, "nodes": [replay]})
    finally:
        broker.stop()


def test_substitutions_includes_conditions_and_flow_order(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 24)
    write_yaml(tmp_path / "inner.yaml", {
        "args": {"src": {}, "out": {"default": "$(dirname)/inner.mcap"}, "with_relay": {"default": False}},
        "nodes": [
            {"name": "replay", "plugin": "marker_replay", "params": {"file": "$(arg src)"}},
            {"name": "relay", "plugin": "relay", "if": "$(arg with_relay)", "params": {"input": "markers/raw", "output": "markers/copy"}},
            {"name": "rec", "plugin": "recorder", "params": {"out": "$(arg out)", "topics": ["markers/raw", "log/"]}},
        ],
    })
    outer = write_yaml(tmp_path / "outer.yaml", {
        "args": {"cap": {}, "relay": {"default": "$(exists $(arg cap))"}},
        "include": [{"file": "inner.yaml", "args": {"src": "$(arg cap)", "with_relay": "$(arg relay)"}}],
        "nodes": [{"name": "viewer", "plugin": "viewer", "unless": True}],
    })
    g = validate(load_launch(outer, {"cap": str(cap)}))
    assert [n.spec.name for n in g.nodes] == ["replay", "relay", "rec"]
    assert g.nodes[2].config.out == str(tmp_path / "inner.mcap")
    assert g.expect["replay"] == {"markers/raw": ["rec", "relay"]}
    assert flow_levels(g) == [["replay"], ["relay", "rec"]]
    g = validate(load_launch(outer, {"cap": str(cap), "relay": False}))
    assert [n.spec.name for n in g.nodes] == ["replay", "rec"]

    from uuomocap.cli import main as cli

    assert cli(["launch", str(outer), f"cap:={cap}", "--check", "--json"]) == 0
    assert cli(["launch", "record_markers", "--check"]) == 2  # required argument missing: one-line error


def test_shipped_session_graphs_name_missing_plugins(tmp_path):
    session = tmp_path / "session"
    session.mkdir()
    write_capture(session / "markers.c3d", 24)
    F = 10
    write_prior_npz(session / "prior.npz", {
        "rate_hz": np.array(30.0), "stamps_ns": np.arange(F, dtype=np.int64) * 33_333_333,
        "global_orient": np.zeros((F, 3)), "body_pose": np.zeros((F, 23, 3)), "betas": np.zeros((F, 10)),
        "valid": np.ones(F, bool), "confidence": np.ones(F), "camera_frame": np.array(True), "body_model": np.array("open-low")})
    installed = discover_plugins()
    for name in ("replay_session", "offline_solve"):
        spec = load_launch(name, {"session": str(session)})
        assert "prior" in [n.name for n in spec.nodes] and "video_prior" not in [n.name for n in spec.nodes]
        missing = [p for p in ("segmenter", "solver") if p not in installed]
        if not missing:
            validate(spec)
            continue
        with pytest.raises(LaunchError) as exc:
            validate(spec)
        assert len(exc.value.problems) == len(missing), exc.value.problems  # nothing else is wrong
        for p in missing:
            assert f"plugin '{p}' is not installed" in str(exc.value)
    (session / "prior.npz").unlink()
    spec = load_launch("replay_session", {"session": str(session)})
    assert "video_prior" in [n.name for n in spec.nodes] and "prior" not in [n.name for n in spec.nodes]


def test_shipped_graphs_add_the_viewer_on_request():
    """view:=true adds the viewer (on the tracked markers in the live graphs), view_png:= its image."""
    for name, markers in (("live_natnet", "markers/tracked"), ("live_qtm", "markers/tracked")):
        assert "viewer" not in [n.name for n in load_launch(name, {}).nodes]
        spec = load_launch(name, {"view": True, "view_png": "/tmp/view.png"})
        (viewer,) = [n for n in spec.nodes if n.name == "viewer"]
        assert viewer.plugin == "viewer" and viewer.params == {"out_png": "/tmp/view.png"}
        assert viewer.remaps == {"markers/raw": markers}
        validate(spec)
        (viewer,) = [n for n in load_launch(name, {"view": True}).nodes if n.name == "viewer"]
        assert viewer.params == {"out_png": ""}  # a status line only


def make_session(d: Path, seconds: float = 1.5, offset_s: float = 0.1) -> tuple[int, np.ndarray]:
    d.mkdir(parents=True, exist_ok=True)
    T = int(seconds * 120)
    write_capture(d / "markers.c3d", T)
    F = int(seconds * 30)
    stamps = np.arange(F, dtype=np.int64) * 33_333_333
    write_prior_npz(d / "prior.npz", {
        "rate_hz": np.array(30.0), "stamps_ns": stamps, "global_orient": np.zeros((F, 3)),
        "body_pose": np.random.default_rng(1).normal(size=(F, 23, 3)) * 0.1, "betas": np.zeros((F, 10)),
        "valid": np.ones(F, bool), "confidence": np.linspace(0.5, 1, F), "camera_frame": np.array(True), "body_model": np.array("open-low")})
    (d / "session.yaml").write_text(yaml.safe_dump({"format": "uuomocap-session/1", "video": {"rate_hz": 30.0, "clock_offset_s": offset_s}}))
    return T, stamps


@pytest.mark.parametrize("lockstep", [False, True])
def test_prior_replay_follows_the_marker_clock(tmp_path, lockstep):
    T, video_stamps = make_session(tmp_path / "s")
    out = tmp_path / "s.mcap"
    replay_acks = ["rec", "rec:body/prior"] if lockstep else ["rec"]
    g = write_yaml(tmp_path / "prior.yaml", {"nodes": [
        {"name": "replay", "plugin": "marker_replay", "on_exit": "shutdown",
         "params": {"file": str(tmp_path / "s" / "markers.c3d"), "speed": 2.0, "lockstep": lockstep, "ack_from": replay_acks}},
        {"name": "prior", "plugin": "prior_replay", "params": {"file": str(tmp_path / "s" / "prior.npz"), "lockstep": lockstep, "ack_from": ["rec"]}},
        {"name": "rec", "plugin": "recorder", "params": {"out": str(out), "topics": ["markers/raw", "body/prior"]}},
    ]})
    proc = start_launch(tmp_path, g, tag="prior")
    assert finish(proc) == 0, _logs(proc)
    envs = recorded(out)
    priors = [e for e in envs if e.type == "BodyPrior"]
    markers = [e for e in envs if e.type == "MarkerFrame"]
    assert len(markers) == T
    offset = 100_000_000  # session.yaml video.clock_offset_s
    # following the marker clock, the replay ends with the markers; in lockstep the prior runs ahead
    expected = video_stamps if lockstep else video_stamps[video_stamps + offset <= markers[-1].stamp_ns]
    assert [p.message.video_stamp_ns for p in priors] == expected.tolist() and len(expected) >= 40
    assert all(p.stamp_ns == p.message.video_stamp_ns + offset for p in priors)
    assert priors[3].message.confidence == pytest.approx(np.linspace(0.5, 1, len(video_stamps))[3])
    order = {id(e): i for i, e in enumerate(envs)}
    for p in priors:
        first_marker_after = next((m for m in markers if m.stamp_ns >= p.stamp_ns), None)
        if first_marker_after is None:
            assert lockstep
        elif lockstep:  # the recorder holds every prior up to a frame's stamp before that frame arrives
            assert order[id(p)] < order[id(first_marker_after)]
        else:  # a prior is released once the marker clock reached it
            assert p.publish_ns >= first_marker_after.publish_ns


# ------------------------------------------------------------------------------------------
# Slow joiners (in-process nodes on threads)
# ------------------------------------------------------------------------------------------


def test_publisher_waits_for_a_late_subscriber_and_loses_nothing(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 60)
    ep = Endpoints.ipc(tmp_path)
    broker = BrokerThread(ep)
    replay = MarkerReplay("replay", MarkerReplay.parse_config({"file": str(cap), "speed": 4.0, "ack_from": ["late"]}, "replay"),
                          Runtime(ep, expect={"markers/raw": ["late"]}, ready_timeout_s=60))
    rec = Recorder("late", Recorder.parse_config({"out": str(tmp_path / "late.mcap"), "topics": ["markers/raw"]}, "late"),
                   Runtime(ep, ack=True))
    codes = {}
    t_replay = threading.Thread(target=lambda: codes.setdefault("replay", replay.run()))
    t_rec = threading.Thread(target=lambda: codes.setdefault("rec", rec.run()))
    try:
        t_replay.start()
        time.sleep(1.0)  # the subscriber joins late on purpose (setup, not an assertion)
        t_rec.start()
        t_replay.join(DEADLINE)
        rec.request_stop()
        t_rec.join(DEADLINE)
    finally:
        replay.request_stop()
        rec.request_stop()
        broker.stop()
    assert codes == {"replay": 0, "rec": 0}
    frames = recorded(tmp_path / "late.mcap", "markers/raw")
    assert [e.seq for e in frames if e.type == "MarkerFrame"] == list(range(60))
    assert replay.counters.get("ready_timeouts", 0) == 0


def test_real_time_replay_starts_its_clock_after_a_late_subscriber(tmp_path):
    """No start-up burst: the frames are paced at the capture rate from the first one published
    (asserted on publish stamps against capture stamps: the pacer never publishes early)."""
    cap = tmp_path / "m.c3d"
    write_capture(cap, 90)  # 0.75 s at 120 Hz
    ep = Endpoints.ipc(tmp_path)
    broker = BrokerThread(ep)
    replay = MarkerReplay("replay", MarkerReplay.parse_config({"file": str(cap)}, "replay"),
                          Runtime(ep, expect={"markers/raw": ["late"]}, ready_timeout_s=60))
    rec = Recorder("late", Recorder.parse_config({"out": str(tmp_path / "late.mcap"), "topics": ["markers/raw"]}, "late"),
                   Runtime(ep))
    codes = {}
    t_replay = threading.Thread(target=lambda: codes.setdefault("replay", replay.run()))
    t_rec = threading.Thread(target=lambda: codes.setdefault("rec", rec.run()))
    try:
        t_replay.start()
        time.sleep(1.5)  # the subscriber joins after the whole capture's duration (setup, not an assertion)
        t_rec.start()
        t_replay.join(DEADLINE)
        rec.request_stop()
        t_rec.join(DEADLINE)
    finally:
        replay.request_stop()
        rec.request_stop()
        broker.stop()
    assert codes == {"replay": 0, "rec": 0}
    frames = [e for e in recorded(tmp_path / "late.mcap", "markers/raw") if e.type == "MarkerFrame"]
    assert [e.seq for e in frames] == list(range(90))
    pub = np.array([e.publish_ns for e in frames], dtype=np.int64)
    cap_ns = np.array([e.stamp_ns for e in frames], dtype=np.int64)
    period = int(np.median(np.diff(cap_ns)))
    # frame k goes out no earlier than its capture offset after frame 0 (tolerance: 3 periods for
    # frame 0 leaving late); a burst would put all 90 frames within a few ms of each other
    assert ((pub - pub[0]) >= (cap_ns - cap_ns[0]) - 3 * period).all()
    assert np.median(np.diff(pub)) > 0.5 * period


# ------------------------------------------------------------------------------------------
# Launched graphs (separate processes)
# ------------------------------------------------------------------------------------------


def test_record_markers_lockstep_is_complete_and_reproducible(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 150)
    runs = []
    for i in range(2):
        out = tmp_path / f"run{i}.mcap"
        proc = start_launch(tmp_path, "record_markers", f"markers:={cap}", f"out:={out}", "lockstep:=true", "window:=4", tag=f"r{i}")
        assert finish(proc) == 0, _logs(proc)
        info = recording_info(out)
        assert info.finished and not info.truncated
        runs.append(recorded(out))
    frames = [e for e in runs[0] if e.type == "MarkerFrame"]
    assert [e.seq for e in frames] == list(range(150))
    assert content(runs[0]) == content(runs[1])
    md, ref = read_markers(tmp_path / "run0.mcap"), read_markers(cap)
    assert md.n_frames == 150 and np.array_equal(md.visible, ref.visible)
    assert np.allclose(np.nan_to_num(md.positions), np.nan_to_num(ref.positions), atol=1e-6)


def test_lockstep_play_to_recorder_exports_identical_npz(tmp_path):
    src = tmp_path / "solved_src.mcap"
    w = RecordingWriter(src)
    rng = np.random.default_rng(3)
    for i in range(40):
        for kind in ("estimate", "refined") if i < 35 else ("estimate",):
            msg = SolvedFrame(stamp_ns=i * 8_333_333, frame_index=i, kind=kind, betas=np.zeros(16, np.float32),
                              poses=rng.normal(size=72).astype(np.float32), trans=rng.normal(size=3).astype(np.float32),
                              joints=rng.normal(size=(24, 3)).astype(np.float32), marker_faces=np.arange(4, dtype=np.int32),
                              marker_bary=np.full((4, 3), 0.25, np.float32), marker_parts=["left_leg"] * 4, rate_hz=120.0)
            from uuomocap.protocol.envelope import decode

            w.write(decode(encode("body/solved", msg, seq=i, stamp_ns=msg.stamp_ns, source="solver", instance=1)))
    w.close()
    npz = []
    for i in range(2):
        out = tmp_path / f"play{i}.mcap"
        g = write_yaml(tmp_path / f"play{i}.yaml", {"nodes": [
            {"name": "play", "plugin": "play", "params": {"file": str(src), "lockstep": True, "ack_from": ["rec"]}, "on_exit": "shutdown"},
            {"name": "rec", "plugin": "recorder", "params": {"out": str(out), "topics": ["body/solved"], "method": "stream-test"}},
        ]})
        proc = start_launch(tmp_path, g, tag=f"p{i}")
        assert finish(proc) == 0, _logs(proc)
        npz.append(out.with_suffix(".npz").read_bytes())
    assert npz[0] == npz[1]
    with np.load(tmp_path / "play0.npz", allow_pickle=False) as z:
        assert z["poses"].shape == (40, 72) and z["frame_kind"].tolist().count("refined") == 35
        assert str(z["method"]) == "stream-test"


def test_killed_node_is_respawned_and_recording_continues(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 6 * 60, rate=60.0)
    out = tmp_path / "relayed.mcap"
    g = write_yaml(tmp_path / "relay.yaml", {"nodes": [
        {"name": "replay", "plugin": "marker_replay", "params": {"file": str(cap), "ack_from": ["relay"]}, "on_exit": "shutdown"},
        {"name": "relay", "plugin": "relay", "params": {"input": "markers/raw", "output": "markers/relayed"},
         "respawn": {"policy": "on-failure", "max_retries": 2, "backoff_s": 0.2}},
        {"name": "rec", "plugin": "recorder", "params": {"out": str(out), "topics": ["markers/relayed"], "flush_interval_s": 0.2},
         "nice": 5},
    ]})
    proc = start_launch(tmp_path, g, tag="k")
    try:
        info = graph_json(proc, "relay", 3)
        relay_pid = next(n["pid"] for n in info["nodes"] if n["name"] == "relay")
        rec_pid = next(n["pid"] for n in info["nodes"] if n["name"] == "rec")
        # 'nice: 5' lowers that node's CPU priority only
        assert os.getpriority(os.PRIO_PROCESS, rec_pid) == min(19, os.getpriority(os.PRIO_PROCESS, relay_pid) + 5)
        poll(lambda: len(recorded(out)) >= 30, "30 relayed frames")
        os.kill(relay_pid, signal.SIGKILL)
        code = finish(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    log = (proc.logs / "launcher.log").read_text()
    assert "node 'relay' ended (signal SIGKILL); respawning" in log, log
    frames = recorded(out)
    instances = [e.instance for e in frames if e.type == "MarkerFrame"]
    assert len(set(instances)) == 2, "frames from the relay before and after its respawn"
    after = [e for e in frames if e.type == "MarkerFrame" and e.instance == instances[-1]]
    assert len(after) >= 30 and after[-1].message.frame_index == 6 * 60  # relayed up to the last frame
    assert code == 0


def test_sigkill_recorder_then_launcher_leaves_readable_file_and_no_process(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 240)
    out = tmp_path / "loop.mcap"
    proc = start_launch(tmp_path, "record_markers", f"markers:={cap}", f"out:={out}", "loop:=true", tag="s")
    try:
        info = graph_json(proc, "record_markers", 2)
        rec_pid = next(n["pid"] for n in info["nodes"] if n["name"] == "recorder")
        # the introspection CLI on the running graph
        gname = f"record_markers-{proc.pid}"  # the runtime dir name selects this graph
        cli = [sys.executable, "-m", "uuomocap.cli"]
        hz = json.loads(subprocess.run([*cli, "topic", "hz", "markers/raw", "--graph", gname, "--duration", "1.5", "--json"],
                                       capture_output=True, text=True, timeout=DEADLINE).stdout)
        # 120 Hz for 1.5 s from the first message received (the window used to open at the subscription,
        # which a loaded machine's slow join left empty: 0 messages in session 43's CI beside two solves)
        assert hz["messages"] > 90 and hz["gaps"] == 0 and 80 < hz["rate_publish_hz"] < 160
        health = json.loads(subprocess.run([*cli, "graph", "--graph", gname, "--duration", "2.5", "--json"],
                                           capture_output=True, text=True, timeout=DEADLINE).stdout)
        states = {n["name"]: n["state"] for n in health["nodes"]}
        assert states == {"replay": "running", "recorder": "running"}
        assert health["topics"]["markers/raw"] == {"publishers": ["replay"], "subscribers": ["recorder"]}
        seen = poll(lambda: len(recorded(out)) >= 120 and len(recorded(out)), "flushed chunks")
        os.kill(rec_pid, signal.SIGKILL)
        poll(lambda: not alive(rec_pid), "recorder to die")
        after_kill = recording_info(out)
        assert not after_kill.finished and after_kill.messages >= seen
        seqs = [e.seq for e in recorded(out, "markers/raw")]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        respawned = out.with_name("loop.respawn1.mcap")
        poll(lambda: len(recorded(respawned)) > 0, "the respawned recorder's file")

        info = graph_json(proc, "record_markers", 2)
        pids = [n["pid"] for n in info["nodes"]] + [info["broker_pid"]]
        assert all(alive(p) for p in pids)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        poll(lambda: not any(alive(p) for p in pids) and not group_members(info["pgid"]), "every graph process to die", timeout=30)
        from uuomocap.launcher import find_running_graphs

        assert all(g["name"] != f"record_markers-{proc.pid}" for g in find_running_graphs())
        assert not (runtime_root() / f"record_markers-{proc.pid}").exists()  # the stale runtime dir was swept
    finally:
        if proc.poll() is None:
            proc.kill()


def test_malformed_messages_are_counted_while_the_graph_runs(tmp_path):
    cap = tmp_path / "m.c3d"
    write_capture(cap, 5 * 60, rate=60.0)
    out = tmp_path / "fuzz.mcap"
    png = tmp_path / "view.png"
    g = write_yaml(tmp_path / "fuzz.yaml", {"nodes": [
        {"name": "replay", "plugin": "marker_replay", "params": {"file": str(cap), "ack_from": ["rec"]}, "on_exit": "shutdown"},
        {"name": "rec", "plugin": "recorder", "params": {"out": str(out), "topics": ["markers/raw", "diag/rec"], "flush_interval_s": 0.2}},
        {"name": "view", "plugin": "viewer", "params": {"out_png": str(png), "period_s": 0.3, "status": False}},
    ]})
    proc = start_launch(tmp_path, g, tag="f")
    pub = sub = None
    try:
        info = graph_json(proc, "fuzz", 3)
        poll(lambda: len(recorded(out, "markers/raw")) >= 10, "the recorder to record")
        pub, sub = Publisher(info["endpoints"]["frontend"], "fuzzer"), Subscriber(info["endpoints"]["backend"])
        sub.subscribe("markers/raw")
        end = time.monotonic() + DEADLINE
        while not any(e.type == "Probe" for e in sub.recv(50)):  # our path to the broker is live
            pub.send_probe("markers/raw", 1)
            assert time.monotonic() < end
        good = [bytes(f) for f in encode("markers/raw", MarkerFrame(stamp_ns=0, frame_index=0, positions=np.zeros((2, 3), np.float32),
                                                                   visible=np.ones(2, bool)), seq=0, stamp_ns=0, source="fuzzer", instance=1)]
        rng = np.random.default_rng(0)
        for i in range(25):
            pub.send_raw([good[0], good[1], good[2][: int(rng.integers(0, 24))], good[3]])  # wrong sizes
            hdr = bytearray(good[1])
            hdr[int(rng.integers(2, len(hdr)))] ^= 0xFF
            pub.send_raw([good[0], bytes(hdr), *good[2:]])  # fuzzed header (rejected or not, never fatal)

        def rejected():
            diags = [e.message for e in recorded(out, "diag/rec")]
            return diags and diags[-1].counters.get("rejected", 0) >= 25

        poll(rejected, "the recorder's diagnostics to count the rejects")
        assert finish(proc) == 0, _logs(proc)
    finally:
        for s in (pub, sub):
            if s is not None:
                s.close()
        if proc.poll() is None:
            proc.kill()
    frames = [e for e in recorded(out, "markers/raw") if e.type == "MarkerFrame"]
    replayed = [e.seq for e in frames if e.source == "replay"]
    assert replayed == list(range(5 * 60)), "every valid frame recorded despite the garbage"
    assert png.is_file() and png.stat().st_size > 1000
    assert "rejected message on 'markers/raw'" in (proc.logs / "rec.log").read_text()


def test_viewer_draws_skeleton_and_markers(tmp_path):
    import cv2

    from uuomocap.nodes.viewer import Viewer, project

    assert np.allclose(project(np.array([[1.0, 2.0, 3.0]]), "+z"), [[1.0, 3.0]])
    assert np.allclose(project(np.array([[1.0, 2.0, 3.0]]), "+y"), [[1.0, 2.0]])
    cfg = Viewer.parse_config({"out_png": str(tmp_path / "v.png"), "status": False}, "view")
    v = Viewer("view", cfg, Runtime(Endpoints.ipc(tmp_path)))
    v.setup()
    joints = np.zeros((24, 3), np.float32)
    joints[:, 2] = np.linspace(0.1, 1.7, 24)  # a vertical "body"
    v.solved = SolvedFrame(stamp_ns=0, frame_index=0, kind="estimate", betas=np.zeros(10, np.float32), poses=np.zeros(72, np.float32),
                           trans=np.zeros(3, np.float32), joints=joints)
    v.markers = MarkerFrame(stamp_ns=0, frame_index=0, positions=joints[:5] + 0.05, visible=np.ones(5, bool))
    v.draw(str(tmp_path / "v.png"))
    img = cv2.imread(str(tmp_path / "v.png"))
    assert img.shape == (480, 480, 3)
    red = (img[:, :, 2] > 150) & (img[:, :, 0] < 100) & (img[:, :, 1] < 100)
    green = (img[:, :, 1] > 100) & (img[:, :, 0] < 100) & (img[:, :, 2] < 100)
    assert red.sum() > 20 and green.sum() > 100  # markers drawn as dots, bones as lines
    # a past frame revised after a lock upgrade is for the recording; the view stays on the live frame
    import types

    live = v.solved
    v.on_solved(dataclasses.replace(live, kind="revised", frame_index=-5), types.SimpleNamespace(publish_ns=0))
    assert v.solved is live
    v.on_solved(dataclasses.replace(live, frame_index=1), types.SimpleNamespace(publish_ns=0))
    assert v.solved.frame_index == 1
    # while estimates flow, a refined frame (a fixed lag behind) does not replace the newest one
    v.on_solved(dataclasses.replace(live, kind="refined", frame_index=-9), types.SimpleNamespace(publish_ns=0))
    assert v.solved.frame_index == 1
    # the markers drawn are the drawn body's frame's when the viewer kept them, not the newest
    env = types.SimpleNamespace(publish_ns=0)
    for i in (1, 2, 3):
        v.on_markers(MarkerFrame(stamp_ns=i, frame_index=i, positions=joints[:5] + 0.01 * i, visible=np.ones(5, bool)), env)
    assert v.drawn_markers().frame_index == 1
    v._estimate_at -= 2.0  # the estimates stopped (the take's end): refined frames are the newest news
    v.on_solved(dataclasses.replace(live, kind="refined", frame_index=7), env)
    assert v.solved.frame_index == 7 and v.drawn_markers().frame_index == 3  # frame 7's markers were never seen
    # with a namer in the graph: the solved frame's named markers, drawn with their names
    def label_pixels(path):
        im = cv2.imread(str(path))
        return int(((im[:, :, 0] > 120) & (im[:, :, 1] < 100) & (im[:, :, 2] < 60)).sum())

    v.draw(str(tmp_path / "unnamed.png"))
    assert label_pixels(tmp_path / "unnamed.png") == 0 and "named" not in v.status_line()
    names = ["LASI", "RASI", "", "LKNE", "RKNE"]
    visible = np.array([True, True, True, False, True])
    named = MarkerFrame(stamp_ns=7, frame_index=7, positions=joints[:5] + 0.02, visible=visible, labels=names)
    v.on_named(named, env)
    assert v.drawn_markers() is named
    v.draw(str(tmp_path / "named.png"))
    assert label_pixels(tmp_path / "named.png") > 10  # three names
    assert "| named 3 |" in v.status_line()  # LASI, RASI, RKNE: the empty name and the hidden LKNE do not count
    # a hidden marker's name and an empty name are not drawn (the one visible slot here is unnamed)
    v.on_named(dataclasses.replace(named, visible=np.array([False, False, True, False, False])), env)
    v.draw(str(tmp_path / "hidden.png"))
    assert label_pixels(tmp_path / "hidden.png") == 0 and "| named 0 |" in v.status_line()
