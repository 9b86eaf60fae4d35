"""Node base class: one process of the streaming graph.

A node declares its parameters (a dataclass ``Config``), its input ports
(``SUBSCRIBES``: port -> :class:`Port`) and output ports (``PUBLISHES``:
port -> topic), and implements hooks. The base class owns everything else:

- sockets (one PUB, one SUB on the broker), topic remaps from the launch file;
- the run loop: receive -> ``on_<port>(msg, env)`` -> publish; or, for sources,
  repeated ``step()`` calls; an optional periodic ``on_timer()``;
- heartbeat on ``heartbeat/<node>``, counters on ``diag/<node>``, Python logging
  forwarded to ``log/<node>`` (and stderr);
- the slow-joiner handshake: before the first message on an output topic, the
  node sends :class:`Probe` messages on that topic until every subscriber the
  launcher declared for it answered :class:`Ready` (``ready/<node>``). A probe
  that arrives proves the whole publisher -> broker -> subscriber path, so no
  data is lost to late joiners. Nodes answer probes even while they wait
  themselves, so cycles in the graph cannot deadlock;
- lockstep credits: with ``runtime.ack`` the node publishes an :class:`Ack` on
  ``ack/<node>`` after handling each data message; sources wait on them with
  :meth:`wait_for_credit`;
- robustness: malformed messages are counted and logged (rate-limited), a
  handler exception is logged and counted, never fatal; SIGINT/SIGTERM stop
  gracefully (a second signal, or ``STOP_TIMEOUT_S`` via SIGALRM, ends it hard).

A minimal processing node::

    @dataclass(frozen=True)
    class ScaleConfig:
        factor: float = 1.0

    class Scale(Node):
        Config = ScaleConfig
        SUBSCRIBES = {"markers": Port("markers/raw", types=("MarkerFrame",))}
        PUBLISHES = {"scaled": "markers/scaled"}

        def on_markers(self, msg, env):
            self.publish("scaled", dataclasses.replace(msg, positions=msg.positions * self.config.factor))
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any, ClassVar

from uuomocap.protocol.envelope import Envelope
from uuomocap.protocol.messages import CONTROL_TYPES, Ack, Diagnostics, EndOfStream, Heartbeat, Log, Message, Ready
from uuomocap.protocol.transport import KEEP_ALL, KEEP_ALL_HWM, LATEST, LATEST_HWM, Endpoints, Publisher, Subscriber

from .config import ConfigError, NoConfig, parse_config

ENTRY_POINT_GROUP = "uuomocap.nodes"


@dataclass(frozen=True)
class Port:
    """An input: topic (or prefix pattern 'a/' / '*'), accepted message types, queue policy.

    optional: the launcher does not insist that some node publishes it.
    """

    topic: str
    types: tuple[str, ...] = ()
    policy: str = KEEP_ALL
    optional: bool = False

    @property
    def is_pattern(self) -> bool:
        return self.topic == "*" or self.topic.endswith(("/", "/*"))


@dataclass(frozen=True)
class Runtime:
    """How a node is wired into a running graph (set by the launcher or a CLI tool)."""

    endpoints: Endpoints
    session: str = ""
    remaps: dict[str, str] = field(default_factory=dict)
    expect: dict[str, list[str]] = field(default_factory=dict)  # topic -> subscriber nodes to wait for
    ack: bool = False
    incarnation: int = 0
    ready_timeout_s: float = 30.0
    plugin: str = ""


class PluginError(LookupError):
    """A plugin name that no installed package provides."""


def discover_plugins() -> dict[str, Any]:
    """Entry points of group ``uuomocap.nodes`` by name (not yet imported)."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_plugin(name: str) -> type["Node"]:
    eps = discover_plugins()
    if name not in eps:
        avail = ", ".join(sorted(eps)) or "none"
        raise PluginError(f"plugin '{name}' is not installed (entry point group {ENTRY_POINT_GROUP} has: {avail})")
    cls = eps[name].load()
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise PluginError(f"plugin '{name}' ({eps[name].value}) is not a uuomocap Node class")
    return cls


class Pacer:
    """Maps source times (ns) to monotonic deadlines at ``speed`` x real time; first call sets the origin."""

    def __init__(self, speed: float = 1.0):
        self.speed = speed
        self._origin: tuple[int, int] | None = None

    def due_ns(self, t_ns: int) -> int:
        if self._origin is None:
            self._origin = (time.monotonic_ns(), t_ns)
        return self._origin[0] + int((t_ns - self._origin[1]) / self.speed)


class _LogPublisher(logging.Handler):
    def __init__(self, node: "Node"):
        super().__init__(logging.INFO)
        self._node = node
        self._busy = threading.local()

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(self._busy, "on", False) or self._node._pub is None:
            return
        self._busy.on = True
        try:
            text = record.getMessage()
            if record.exc_info:
                text += "\n" + logging.Formatter().formatException(record.exc_info)
            self._node._pub.send(f"log/{self._node.name}", Log(self._node.name, record.levelno, text[:8000], record.name), time.monotonic_ns())
        except Exception:  # logging must never take a node down
            pass
        finally:
            self._busy.on = False


class Node:
    Config: ClassVar[type] = NoConfig
    SUBSCRIBES: ClassVar[dict[str, Port | str]] = {}
    PUBLISHES: ClassVar[dict[str, str]] = {}
    HEARTBEAT_S: ClassVar[float] = 1.0
    DIAG_S: ClassVar[float] = 2.0
    TIMER_S: ClassVar[float | None] = None  # period of on_timer(), None = never
    DRAIN_ON_STOP_S: ClassVar[float] = 0.0  # sinks: keep handling until the input is idle this long
    DRAIN_MAX_S: ClassVar[float] = 2.0  # ... but never longer than this
    FINISH_LINGER_MS: ClassVar[int] = 2000  # how long a node that finished by itself lets its last messages leave
    STOP_TIMEOUT_S: ClassVar[int] = 10  # after a stop request, SIGALRM ends the process
    ACK_REPEAT_S: ClassVar[float] = 0.2  # period of re-sending the latest acks (lockstep)

    # ---- ports --------------------------------------------------------------------------
    @classmethod
    def ports(cls, config: Any) -> tuple[dict[str, Port], dict[str, str]]:
        """(inputs, outputs) before remapping. Override when topics come from the config."""
        subs = {k: v if isinstance(v, Port) else Port(v) for k, v in cls.SUBSCRIBES.items()}
        return subs, dict(cls.PUBLISHES)

    @classmethod
    def remapped_ports(cls, config: Any, remaps: dict[str, str]) -> tuple[dict[str, Port], dict[str, str]]:
        subs, pubs = cls.ports(config)
        subs = {k: Port(remaps.get(p.topic, p.topic), p.types, p.policy, p.optional) for k, p in subs.items()}
        return subs, {k: remaps.get(t, t) for k, t in pubs.items()}

    @classmethod
    def parse_config(cls, params: dict | None, where: str) -> Any:
        return parse_config(cls.Config, params, where)

    # ---- construction -------------------------------------------------------------------
    def __init__(self, name: str, config: Any, runtime: Runtime):
        self.name = name
        self.config = config
        self.runtime = runtime
        self.inputs, self.outputs = self.remapped_ports(config, runtime.remaps)
        self.log = logging.getLogger(f"uuomocap.node.{name}")
        self.counters: dict[str, int] = defaultdict(int)
        self.timer_s = self.TIMER_S
        self._pub: Publisher | None = None
        self._sub: Subscriber | None = None
        self._pending: deque[Envelope] = deque()
        self._stop = False
        self._exit_code = 0
        self._started = time.monotonic()
        self._state = "starting"
        self._ready_done: set[str] = set()
        self._readies: dict[str, set[str]] = defaultdict(set)
        self._acks: dict[tuple[str, str], tuple[int, int, bool]] = {}  # (node, topic) -> (seq, stamp, eos)
        self._ack_nodes: set[str] = set()
        self._due: dict[str, float] = {}
        self._reject_logged: dict[str, int] = defaultdict(int)
        self._in_handler = False
        self._ack_state: dict[tuple[str, str, int], Ack] = {}
        self._sent_while_stopping = False

    # ---- hooks for subclasses -----------------------------------------------------------
    def setup(self) -> None:
        """Load models / files. Raising here ends the process with exit code 1."""

    def step(self) -> bool | None:
        """Source nodes: produce the next piece of output; return False when finished."""
        raise NotImplementedError

    def on_message(self, port: str, msg: Message, env: Envelope) -> None:
        handler = getattr(self, f"on_{port}", None)
        if handler is None:
            raise NotImplementedError(f"{type(self).__name__} has no handler on_{port}(msg, env)")
        handler(msg, env)

    def on_eos(self, port: str, env: Envelope) -> None:
        """The publisher of ``port`` said it has no more data."""

    def on_timer(self) -> None:
        """Called every ``self.timer_s`` seconds when set."""

    def on_stop(self) -> None:
        """Stopped by a signal (after the drain, before teardown): publish what the node still
        holds that downstream should record (the launcher stops nodes in data-flow order, so the
        sinks are still running)."""

    def teardown(self) -> None:
        """Release resources; always called, also after a stop signal."""

    # ---- services ---------------------------------------------------------------------------
    @property
    def stopping(self) -> bool:
        return self._stop

    def request_stop(self, exit_code: int = 0) -> None:
        self._stop = True
        self._exit_code = exit_code

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] += n

    def topic(self, port: str) -> str:
        return self.outputs[port]

    def publish(self, port: str, msg: Message, stamp_ns: int | None = None) -> int:
        """Send ``msg`` on an output port (after the ready handshake for its topic)."""
        topic = self.outputs[port]
        if topic not in self._ready_done:
            self._wait_ready(topic)
        self._sent_while_stopping = self._sent_while_stopping or self._stop
        return self._pub.send(topic, msg, stamp_ns)

    def wait_ready(self, *ports: str) -> None:
        """Run the slow-joiner handshake now for these output ports (default: all of them).

        Paced sources call this before their clock starts: otherwise the first publish() waits
        for the subscribers after the clock's origin was taken, and the frames that fell due
        meanwhile go out in a burst."""
        for port in ports or tuple(self.outputs):
            topic = self.outputs[port]
            if topic not in self._ready_done:
                self._wait_ready(topic)

    def input_waiting(self, port: str) -> bool:
        """From a handler: is another data message for input ``port`` already queued (control
        messages such as the end of the stream do not count)?  Receives what the socket holds
        without blocking (nothing is dispatched while a handler runs), so a node can defer
        optional work while it is behind."""
        self._serve(0)
        return any(e.type not in CONTROL_TYPES and self._port_for(e.topic) == port for e in self._pending)

    def end_stream(self, port: str) -> None:
        topic = self.outputs[port]
        seq, stamp = self._pub.last_sent.get(topic, (-1, 0))
        self.publish(port, EndOfStream(topic=topic, last_seq=seq, last_stamp_ns=stamp), stamp)

    def track_acks(self, nodes: list[str]) -> None:
        """Receive the Acks of these nodes (lockstep sources); call in setup()."""
        for n in nodes:
            if n not in self._ack_nodes:
                self._ack_nodes.add(n)
                self._sub.subscribe(f"ack/{n}")

    def acked(self, node: str, topic: str) -> tuple[int, int, bool] | None:
        return self._acks.get((node, topic))

    def wait_for_credit(self, port: str, seq: int, stamp_ns: int, ack_from: list[str], window: int, timeout_s: float,
                        require_eos: bool = False) -> bool:
        """Block (while serving the sockets) until every entry of ``ack_from`` allows message ``seq``.

        'node': node has acknowledged our message seq - window on this port's topic (with
                require_eos: it has also handled our EndOfStream, i.e. finished its on_eos).
        'node:topic': node has acknowledged a message on topic with stamp >= stamp_ns, or its end.
        Returns False on stop or timeout (counted as ack_timeouts, logged).
        """
        topic = self.outputs[port]
        deadline = time.monotonic() + timeout_s

        def satisfied() -> bool:
            for entry in ack_from:
                node, _, other = entry.partition(":")
                if other:
                    a = self._acks.get((node, self.runtime.remaps.get(other, other)))
                    if a is None or not (a[2] or a[1] >= stamp_ns):
                        return False
                else:
                    a = self._acks.get((node, topic))
                    if seq - window >= 0 and (a is None or a[0] < seq - window):
                        return False
                    if require_eos and (a is None or not a[2]):
                        return False
            return True

        while not satisfied():
            if self._stop:
                return False
            if time.monotonic() > deadline:
                self.count("ack_timeouts")
                self.log.warning("no credit from %s for %s seq %d within %.1fs; going on", ack_from, topic, seq, timeout_s)
                return False
            self._serve(20)
        return True

    def serve(self, timeout_ms: float) -> None:
        """Wait up to timeout_ms for input and handle it (sources that wait for their inputs)."""
        self._serve(timeout_ms)

    @classmethod
    def ack_sources(cls, config: Any) -> list[str]:
        """Nodes whose acks this node waits for (the launcher turns --ack on for them)."""
        return [entry.partition(":")[0] for entry in getattr(config, "ack_from", [])]

    def sleep_until(self, deadline_monotonic_ns: int) -> bool:
        """Wait until the deadline while serving sockets and timers; False if asked to stop."""
        while not self._stop:
            remaining_ms = (deadline_monotonic_ns - time.monotonic_ns()) / 1e6
            if remaining_ms <= 0:
                return True
            self._serve(min(remaining_ms, 50.0))
        return False

    # ---- run ----------------------------------------------------------------------------------
    def run(self) -> int:
        """Run until finished or stopped; returns the process exit code."""
        self._install_signals()
        self._open()
        try:
            try:
                self.setup()
            except Exception:
                self.log.exception("setup failed")
                return 1
            self._state = "running"
            self._heartbeat()
            is_source = type(self).step is not Node.step
            while not self._stop:
                if is_source:
                    self._serve(0)
                    if self.step() is False:
                        break
                else:
                    self._serve(self._next_timer_ms())
            if self.DRAIN_ON_STOP_S > 0:
                self._drain(self.DRAIN_ON_STOP_S)
            if self._stop:
                self.on_stop()
        except Exception:
            self.log.exception("node failed")
            self._exit_code = 1
        finally:
            self._state = "stopping"
            try:
                self.teardown()
            except Exception:
                self.log.exception("teardown failed")
                self._exit_code = self._exit_code or 1
            self._diagnostics()
            self._heartbeat()
            self._close()
        return self._exit_code

    # ---- internals ----------------------------------------------------------------------------
    def _install_signals(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def on_signal(signum, frame):
            if self._stop:
                os._exit(128 + signum)  # second signal: the operator means it
            self._stop = True
            signal.alarm(self.STOP_TIMEOUT_S)  # default SIGALRM action ends a stuck shutdown

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)

    def _open(self) -> None:
        if not logging.getLogger().handlers and not self.log.handlers:
            h = logging.StreamHandler(sys.stderr)
            h.setFormatter(logging.Formatter(f"[{self.name}] %(levelname)s %(message)s"))
            self.log.addHandler(h)
        self.log.setLevel(logging.INFO)
        self.log.addHandler(_LogPublisher(self))
        self._pub = Publisher(self.runtime.endpoints.frontend, self.name, session=self.runtime.session)
        latest_only = bool(self.inputs) and all(p.policy == LATEST for p in self.inputs.values())
        self._sub = Subscriber(
            self.runtime.endpoints.backend, hwm=LATEST_HWM if latest_only else KEEP_ALL_HWM, on_reject=self._on_reject
        )
        for port in self.inputs.values():
            self._sub.subscribe(port.topic, port.policy)
        if any(self.runtime.expect.get(t) for t in self.outputs.values()):
            self._sub.subscribe(f"ready/{self.name}")
        self._exact_port = {p.topic: k for k, p in self.inputs.items() if not p.is_pattern}
        self._prefix_port = [(p.topic.rstrip("*"), k) for k, p in self.inputs.items() if p.is_pattern]

    def _close(self) -> None:
        if self._sub is not None:
            self._sub.close()
        if self._pub is not None:
            # A node that finished by itself (a replay at its end) may still have messages queued in
            # the socket: closing with linger 0 dropped them (a lockstep replay then waited forever
            # for the credit of a prior that never left).  Stopped by a signal: no wait, unless it
            # published while stopping (a drain, on_stop) - those messages are the point of it.
            self._pub.close(0 if self._stop and not self._sent_while_stopping else self.FINISH_LINGER_MS)
        self._pub = self._sub = None

    def _port_for(self, topic: str) -> str | None:
        port = self._exact_port.get(topic)
        if port is None:
            for prefix, k in self._prefix_port:
                if topic.startswith(prefix):
                    return k
        return port

    def _on_reject(self, reason: str, detail: str, topic: str) -> None:
        self.counters["rejected"] += 1
        n = self._reject_logged[reason] = self._reject_logged[reason] + 1
        if n <= 5 or n % 1000 == 0:
            self.log.warning("rejected message on %r (%s, %d so far): %s", topic, reason, n, detail)

    def _serve(self, timeout_ms: float) -> None:
        """Receive (up to timeout), handle control traffic, dispatch data, run due timers."""
        for env in self._sub.recv(int(timeout_ms)):
            t = env.type
            if t == "Probe":
                if self._port_for(env.topic) is not None:
                    p = env.message
                    self._pub.send(f"ready/{p.publisher}", Ready(self.name, p.topic, p.publisher, p.nonce), 0)
                continue
            if t == "Ready" and env.topic == f"ready/{self.name}":
                self._readies[env.message.topic].add(env.message.node)
            elif t == "Ack" and env.message.node in self._ack_nodes:
                a = env.message
                if a.topic not in self.outputs.values() or (a.publisher == self.name and a.instance == self._pub.instance):
                    prev = self._acks.get((a.node, a.topic))
                    if prev is None or a.seq >= prev[0] or a.eos:
                        self._acks[(a.node, a.topic)] = (a.seq, a.stamp_ns, a.eos or (prev is not None and prev[2]))
            if self._port_for(env.topic) is not None:
                self._pending.append(env)
        # never re-enter handlers: a handler waiting in publish() leaves data pending
        while self._pending and not self._in_handler and not (self._stop and self.DRAIN_ON_STOP_S == 0):
            self._dispatch(self._pending.popleft())
        self._timers()

    def _dispatch(self, env: Envelope) -> None:
        port = self._port_for(env.topic)
        if env.type == "EndOfStream":
            self.count("eos")
            self._call(self.on_eos, port, env)
            self._ack(env, eos=True)
            return
        spec = self.inputs[port]
        if spec.types and env.type not in spec.types:
            self._on_reject("wrong_type", f"{env.type} on port {port} (expects {', '.join(spec.types)})", env.topic)
            return
        self.count("handled")
        self._call(self.on_message, port, env.message, env)
        if env.type not in CONTROL_TYPES:
            self._ack(env)

    def _call(self, fn, *args) -> None:
        self._in_handler = True
        try:
            fn(*args)
        except Exception:
            self.count("handler_errors")
            n = self.counters["handler_errors"]
            if n <= 5 or n % 100 == 0:
                self.log.exception("handler %s failed (%d so far)", getattr(fn, "__name__", fn), n)
        finally:
            self._in_handler = False

    def _ack(self, env: Envelope, eos: bool = False) -> None:
        if self.runtime.ack:
            a = Ack(self.name, env.topic, env.source, env.instance, env.seq, env.stamp_ns, eos)
            key = (env.topic, env.source, env.instance)
            prev = self._ack_state.pop(key, None)
            self._ack_state[key] = Ack(**{**a.scalars(), "eos": eos or bool(prev and prev.eos)})
            while len(self._ack_state) > 64:  # forget the oldest publisher instances
                self._ack_state.pop(next(iter(self._ack_state)))
            self._pub.send(f"ack/{self.name}", self._ack_state[key], env.stamp_ns)

    def _wait_ready(self, topic: str) -> None:
        expected = set(self.runtime.expect.get(topic, ()))
        deadline = time.monotonic() + self.runtime.ready_timeout_s
        nonce, interval = 0, 0.02
        while not expected <= self._readies[topic] and not self._stop:
            if time.monotonic() > deadline:
                missing = sorted(expected - self._readies[topic])
                self.count("ready_timeouts")
                self.log.warning("subscribers %s of %s not ready after %.0fs; publishing anyway", missing, topic, self.runtime.ready_timeout_s)
                break
            nonce += 1
            self._pub.send_probe(topic, nonce)
            end = time.monotonic() + interval
            while time.monotonic() < end and not expected <= self._readies[topic]:
                self._serve(10)
            interval = min(interval * 1.5, 0.25)
        self._ready_done.add(topic)

    def _drain(self, idle_s: float) -> None:
        """After a stop request: handle what is still arriving until the input is quiet."""
        last = time.monotonic()
        hard = last + self.DRAIN_MAX_S  # a live stream is never idle: bound the drain
        while time.monotonic() - last < idle_s and time.monotonic() < hard:
            before = self.counters["handled"] + self.counters["eos"]
            self._serve(20)
            if self.counters["handled"] + self.counters["eos"] != before:
                last = time.monotonic()

    def _next_timer_ms(self) -> float:
        now = time.monotonic()
        keys = ["hb", "diag"] + (["timer"] if self.timer_s else []) + (["ack"] if self._ack_state else [])
        due = [self._due.get(k, now) for k in keys]
        return max(0.0, min(100.0, (min(due) - now) * 1000))

    def _timers(self) -> None:
        now = time.monotonic()
        if now >= self._due.get("hb", 0):
            self._due["hb"] = now + self.HEARTBEAT_S
            self._heartbeat()
        if self._ack_state and now >= self._due.get("ack", 0):
            # acks are state: repeat the latest ones so a credit waiter that joined late (or
            # lost one in flight) catches up instead of waiting for its timeout
            self._due["ack"] = now + self.ACK_REPEAT_S
            for a in list(self._ack_state.values()):
                self._pub.send(f"ack/{self.name}", a, a.stamp_ns)
        if now >= self._due.get("diag", 0):
            self._due["diag"] = now + self.DIAG_S
            self._diagnostics()
        if self.timer_s and self._state == "running" and not self._in_handler and now >= self._due.get("timer", 0):
            self._due["timer"] = now + self.timer_s
            self._call(lambda: self.on_timer())

    def _heartbeat(self) -> None:
        if self._pub is None:
            return
        hb = Heartbeat(
            node=self.name,
            plugin=self.runtime.plugin or type(self).__name__,
            pid=os.getpid(),
            state=self._state,
            uptime_s=time.monotonic() - self._started,
            publishes=sorted(self.outputs.values()),
            subscribes=sorted(p.topic for p in self.inputs.values()),
            incarnation=self.runtime.incarnation,
        )
        self._pub.send(f"heartbeat/{self.name}", hb, time.monotonic_ns())

    def diagnostics(self) -> Diagnostics:
        topics: dict[str, dict] = {t: st.as_dict() for t, st in self._sub.stats.items()} if self._sub else {}
        for t, n in (self._pub.sent.items() if self._pub else ()):
            if not t.startswith(("heartbeat/", "diag/", "log/", "ack/", "ready/")):
                topics.setdefault(t, {})["published"] = n
        counters = {k: int(v) for k, v in self.counters.items()}
        rejected = dict(self._sub.rejected) if self._sub else {}
        return Diagnostics(node=self.name, counters=counters, topics=topics, rejected=rejected)

    def _diagnostics(self) -> None:
        if self._pub is not None:
            self._pub.send(f"diag/{self.name}", self.diagnostics(), time.monotonic_ns())


__all__ = [
    "Node",
    "Pacer",
    "Port",
    "Runtime",
    "ConfigError",
    "PluginError",
    "discover_plugins",
    "load_plugin",
    "ENTRY_POINT_GROUP",
    "KEEP_ALL",
    "LATEST",
]
