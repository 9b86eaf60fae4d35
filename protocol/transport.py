"""ZeroMQ transport: a stateless XSUB/XPUB broker, publishers and subscribers.

Topology (Pupil Labs' "backbone" style): every publisher connects a PUB socket
to the broker's *frontend* (XSUB), every subscriber connects a SUB socket to
its *backend* (XPUB). The broker holds no state beyond ZeroMQ's subscription
forwarding, so it can be restarted; peers reconnect and re-send their
subscriptions by themselves.

Endpoints are ``ipc://`` under a per-graph runtime directory on one machine
(default) or ``tcp://`` across a studio network (bound on 127.0.0.1 unless the
launch file says otherwise). Every socket closes with ``linger=0``, except the publisher of a node
that finished by itself, which lets its last queued messages leave (``Node.FINISH_LINGER_MS``).

Queue policy per subscription:
  keep_all  every message in order (recorder); large high-water marks.
  latest    drain whatever is queued and keep only the newest per topic (viewer).
            ZMQ_CONFLATE cannot be used because it breaks multipart messages.

Sequence numbers are tracked per (topic, publisher instance): gaps (messages
lost in flight), messages missed before joining, duplicates / reordering, and
messages superseded by the ``latest`` policy are counted separately.

Slow joiners: see ``nodes.base`` -- a publisher sends :class:`Probe` messages on
each data topic until every declared subscriber answers with :class:`Ready`, so
data is only sent once the whole path is proven live.
"""

from __future__ import annotations

import argparse
import os
import secrets
import socket
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import zmq

from .envelope import DEFAULT_LIMITS, DecodeError, Envelope, Limits, decode, encode
from .messages import CONTROL_TYPES, Message, Probe

KEEP_ALL = "keep_all"
LATEST = "latest"
POLICIES = (KEEP_ALL, LATEST)

#: high-water mark (messages) for keep-all paths: minutes of 120 Hz frames
KEEP_ALL_HWM = 200_000
#: high-water mark for latest-only subscribers: a slow viewer drops at the broker, never stalls it
LATEST_HWM = 1_000


# ------------------------------------------------------------------------------------------
# Endpoints
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Endpoints:
    """frontend: where publishers connect (broker XSUB binds); backend: where subscribers connect."""

    frontend: str
    backend: str

    @classmethod
    def ipc(cls, runtime_dir: str | Path) -> "Endpoints":
        d = Path(runtime_dir)
        return cls(f"ipc://{d / 'pub.sock'}", f"ipc://{d / 'sub.sock'}")

    @classmethod
    def tcp(cls, host: str = "127.0.0.1", frontend_port: int = 5560, backend_port: int = 5561) -> "Endpoints":
        return cls(f"tcp://{host}:{frontend_port}", f"tcp://{host}:{backend_port}")

    @classmethod
    def parse(cls, text: str) -> "Endpoints":
        """'FRONTEND,BACKEND' as given on command lines."""
        parts = [p.strip() for p in text.split(",")]
        if len(parts) != 2 or not all(p.startswith(("ipc://", "tcp://")) for p in parts):
            raise ValueError(f"endpoints must be 'ipc://..|tcp://..,ipc://..|tcp://..', got {text!r}")
        return cls(*parts)

    def __str__(self) -> str:
        return f"{self.frontend},{self.backend}"


def runtime_root() -> Path:
    """Per-user directory holding one sub-directory per running graph."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    root = Path(base) / "uuomocap" if base and Path(base).is_dir() else Path(f"/tmp/uuomocap-{os.getuid()}")
    root.mkdir(mode=0o700, parents=True, exist_ok=True)
    return root


def endpoint_in_use(endpoint: str) -> str | None:
    """Why ``endpoint`` cannot be bound (a live broker or another program holds it), else None.

    A stale ipc socket file (no listener) is not a collision; zmq replaces it on bind.
    """
    if endpoint.startswith("ipc://"):
        path = endpoint[len("ipc://"):]
        if len(path.encode()) > 100:
            return f"ipc path {path!r} is longer than the 100-byte unix socket limit"
        if not os.path.exists(path):
            return None
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(path)
            return f"{endpoint} is in use by another running graph"
        except OSError:
            return None
        finally:
            probe.close()
    if endpoint.startswith("tcp://"):
        hostport = endpoint[len("tcp://"):]
        host, _, port = hostport.rpartition(":")
        if not port.isdigit():
            return f"{endpoint}: port must be a number"
        host = {"*": "0.0.0.0", "localhost": "127.0.0.1"}.get(host, host)
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, int(port)))
            return None
        except OSError as exc:
            return f"{endpoint} cannot be bound: {exc.strerror}"
        finally:
            s.close()
    return f"{endpoint!r} is neither ipc:// nor tcp://"


# ------------------------------------------------------------------------------------------
# Broker
# ------------------------------------------------------------------------------------------


def _broker_sockets(ctx: zmq.Context, frontend: str, backend: str, hwm: int) -> tuple[zmq.Socket, zmq.Socket]:
    xsub = ctx.socket(zmq.XSUB)
    xpub = ctx.socket(zmq.XPUB)
    for s in (xsub, xpub):
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, hwm)
        s.setsockopt(zmq.RCVHWM, hwm)
    xsub.bind(frontend)
    xpub.bind(backend)
    return xsub, xpub


def run_broker(frontend: str, backend: str, *, hwm: int = KEEP_ALL_HWM, context: zmq.Context | None = None) -> None:
    """Forward publishers (frontend) to subscribers (backend) until interrupted or the context ends."""
    ctx = context or zmq.Context.instance()
    xsub, xpub = _broker_sockets(ctx, frontend, backend, hwm)
    try:
        zmq.proxy(xsub, xpub)
    except (KeyboardInterrupt, zmq.ContextTerminated):
        pass
    finally:
        xsub.close(0)
        xpub.close(0)


class BrokerThread:
    """The same broker in a background thread (tests and single-process tools)."""

    def __init__(self, endpoints: Endpoints, hwm: int = KEEP_ALL_HWM):
        self.endpoints = endpoints
        self._ctx = zmq.Context.instance()
        self._ctl_addr = f"inproc://broker-ctl-{secrets.token_hex(6)}"
        self._ctl = self._ctx.socket(zmq.PAIR)
        self._ctl.bind(self._ctl_addr)
        self._bound = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(hwm,), daemon=True, name="uuomocap-broker")
        self._thread.start()
        self._bound.wait(10)
        if self._error:
            raise self._error

    def _run(self, hwm: int) -> None:
        try:
            xsub, xpub = _broker_sockets(self._ctx, self.endpoints.frontend, self.endpoints.backend, hwm)
        except BaseException as exc:  # surfaced to the constructor
            self._error = exc
            self._bound.set()
            return
        ctl = self._ctx.socket(zmq.PAIR)
        ctl.connect(self._ctl_addr)
        self._bound.set()
        try:
            zmq.proxy_steerable(xsub, xpub, None, ctl)
        except zmq.ContextTerminated:
            pass
        finally:
            for s in (xsub, xpub, ctl):
                s.close(0)

    def stop(self) -> None:
        self._ctl.send(b"TERMINATE")
        self._thread.join(5)
        self._ctl.close(0)


# ------------------------------------------------------------------------------------------
# Publisher
# ------------------------------------------------------------------------------------------


class Publisher:
    """PUB socket connected to the broker frontend; numbers messages per topic."""

    def __init__(self, frontend: str, node: str, *, session: str = "", hwm: int = KEEP_ALL_HWM, context: zmq.Context | None = None):
        self.node = node
        self.session = session
        self.instance = secrets.randbits(31)
        self._seq: dict[str, int] = defaultdict(int)
        self.sent: dict[str, int] = defaultdict(int)
        self.last_sent: dict[str, tuple[int, int]] = {}  # topic -> (seq, stamp_ns)
        self._sock = (context or zmq.Context.instance()).socket(zmq.PUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.SNDHWM, hwm)
        self._sock.connect(frontend)

    def send(self, topic: str, message: Message, stamp_ns: int | None = None) -> int:
        """Publish; returns the sequence number used. Validates the message first."""
        if stamp_ns is None:
            stamp_ns = getattr(message, "stamp_ns", None)
            if stamp_ns is None:
                stamp_ns = time.monotonic_ns()
        seq = self._seq[topic]
        frames = encode(topic, message, seq=seq, stamp_ns=stamp_ns, source=self.node, instance=self.instance, session=self.session)
        self._sock.send_multipart(frames, copy=False)
        self._seq[topic] = seq + 1
        self.sent[topic] += 1
        self.last_sent[topic] = (seq, int(stamp_ns))
        return seq

    def next_seq(self, topic: str) -> int:
        return self._seq[topic]

    def send_probe(self, topic: str, nonce: int) -> None:
        """Probes carry seq -1: they are not part of the topic's numbered stream."""
        msg = Probe(topic=topic, publisher=self.node, nonce=nonce)
        frames = encode(topic, msg, seq=-1, stamp_ns=0, source=self.node, instance=self.instance, session=self.session)
        self._sock.send_multipart(frames, copy=False)

    def send_raw(self, frames: list) -> None:
        """Send frames that were already encoded (fuzzing, relays of foreign traffic)."""
        self._sock.send_multipart(frames, copy=False)

    def close(self, linger_ms: int = 0) -> None:
        """Close; ``linger_ms`` > 0 first lets already-sent messages leave the socket for up to
        that long (a node that finished on its own: its last messages must still arrive)."""
        self._sock.close(linger_ms)


# ------------------------------------------------------------------------------------------
# Subscriber
# ------------------------------------------------------------------------------------------


@dataclass
class TopicStats:
    received: int = 0
    bytes: int = 0
    gaps: int = 0  # numbered messages lost between two received ones
    missed_at_join: int = 0  # a publisher's messages sent before we joined
    out_of_order: int = 0  # duplicates or reordering (seq not increasing)
    superseded: int = 0  # dropped on purpose by the latest-only policy
    rejected: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    publishers: set = field(default_factory=set)

    def as_dict(self) -> dict:
        return {
            "received": self.received,
            "bytes": self.bytes,
            "gaps": self.gaps,
            "missed_at_join": self.missed_at_join,
            "out_of_order": self.out_of_order,
            "superseded": self.superseded,
            "rejected": self.rejected,
            "publishers": len(self.publishers),
        }


class Subscriber:
    """SUB socket on the broker backend with exact / prefix topic filters and per-topic policy.

    Topic patterns: ``"a/b"`` exact; ``"a/"`` or ``"a/*"`` every topic under ``a/``; ``"*"`` all.
    ``recv`` never raises on bad input: rejected messages go to ``on_reject`` and the counters.
    """

    def __init__(
        self,
        backend: str,
        *,
        hwm: int = KEEP_ALL_HWM,
        limits: Limits = DEFAULT_LIMITS,
        context: zmq.Context | None = None,
        on_reject: Callable[[str, str, str], None] | None = None,
    ):
        self._sock = (context or zmq.Context.instance()).socket(zmq.SUB)
        self._sock.setsockopt(zmq.LINGER, 0)
        self._sock.setsockopt(zmq.RCVHWM, hwm)
        self._sock.connect(backend)
        self._poller = zmq.Poller()
        self._poller.register(self._sock, zmq.POLLIN)
        self.limits = limits
        self.on_reject = on_reject
        self._exact: dict[str, str] = {}
        self._prefix: list[tuple[str, str]] = []
        self.stats: dict[str, TopicStats] = defaultdict(TopicStats)
        self.rejected: dict[str, int] = defaultdict(int)
        self._last_seq: dict[tuple[str, str, int], int] = {}

    @property
    def socket(self) -> zmq.Socket:
        return self._sock

    def subscribe(self, pattern: str, policy: str = KEEP_ALL) -> None:
        if policy not in POLICIES:
            raise ValueError(f"queue policy must be one of {POLICIES}, got {policy!r}")
        if pattern == "*" or pattern.endswith(("/", "/*")):
            prefix = pattern.rstrip("*")
            self._prefix.append((prefix, policy))
            self._sock.setsockopt(zmq.SUBSCRIBE, prefix.encode())
        else:
            self._exact[pattern] = policy
            self._sock.setsockopt(zmq.SUBSCRIBE, pattern.encode())

    def policy_for(self, topic: str) -> str | None:
        if topic in self._exact:
            return self._exact[topic]
        for prefix, policy in self._prefix:
            if topic.startswith(prefix):
                return policy
        return None

    def wait(self, timeout_ms: int) -> bool:
        return bool(self._poller.poll(max(0, int(timeout_ms))))

    def recv(self, timeout_ms: int = 0, max_batch: int = 1000) -> list[Envelope]:
        """Messages available within ``timeout_ms`` (all queued ones, up to max_batch)."""
        if not self._poller.poll(max(0, int(timeout_ms))):
            return []
        out: list[Envelope] = []
        latest: dict[str, int] = {}
        for _ in range(max_batch):
            try:
                frames = self._sock.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            env = self._accept(frames)
            if env is None:
                continue
            if env.type not in CONTROL_TYPES and self.policy_for(env.topic) == LATEST:
                if env.topic in latest:
                    out[latest[env.topic]] = None  # type: ignore[call-overload]
                    self.stats[env.topic].superseded += 1
                latest[env.topic] = len(out)
            out.append(env)
        return [e for e in out if e is not None]

    def _accept(self, frames: list) -> Envelope | None:
        topic_guess = ""
        try:
            topic_guess = bytes(frames[0].buffer[:200]).decode("utf-8", "replace")
            env = decode(frames, self.limits)
        except DecodeError as exc:
            self.rejected[exc.reason] += 1
            if self.policy_for(topic_guess) is not None:
                self.stats[topic_guess].rejected += 1
            if self.on_reject:
                self.on_reject(exc.reason, exc.detail, topic_guess)
            return None
        if self.policy_for(env.topic) is None:
            return None  # prefix match of a longer topic name we did not ask for
        if env.seq >= 0:
            self._count(env)
        return env

    def _count(self, env: Envelope) -> None:
        st = self.stats[env.topic]
        key = (env.topic, env.source, env.instance)
        last = self._last_seq.get(key)
        if last is None:
            st.missed_at_join += env.seq
            st.publishers.add((env.source, env.instance))
        elif env.seq > last + 1:
            st.gaps += env.seq - last - 1
        elif env.seq <= last:
            st.out_of_order += 1
        if last is None or env.seq > last:
            self._last_seq[key] = env.seq
        st.received += 1
        st.bytes += env.nbytes
        if st.first_stamp_ns is None:
            st.first_stamp_ns = env.stamp_ns
        st.last_stamp_ns = env.stamp_ns

    def close(self) -> None:
        self._sock.close(0)


def main(argv: list[str] | None = None) -> int:
    """``python -m uuomocap.protocol.transport --frontend EP --backend EP``: run a broker process."""
    parser = argparse.ArgumentParser(prog="uuomocap-broker", description=run_broker.__doc__)
    parser.add_argument("--frontend", required=True, help="publishers connect here (XSUB binds)")
    parser.add_argument("--backend", required=True, help="subscribers connect here (XPUB binds)")
    parser.add_argument("--hwm", type=int, default=KEEP_ALL_HWM)
    args = parser.parse_args(argv)
    run_broker(args.frontend, args.backend, hwm=args.hwm)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
