"""Launch a graph from a YAML launch file: validate everything, then spawn and supervise.

Launch file (``launch/*.yaml``)::

    name: record_markers                 # optional, default: file stem
    args:                                # overridable on the command line as key:=value
      markers: {help: "marker file"}     # no default: required
      speed: {default: 1.0}
    transport: {kind: ipc}               # or {kind: tcp, host: 127.0.0.1, frontend_port: 5560, backend_port: 5561}
                                         # ipc may name a fixed dir: {kind: ipc, dir: /path}
    external_topics: [markers/live]      # published by something outside this graph
    include:
      - {file: other.yaml, args: {x: $(arg x)}, if: $(arg use_other)}
    nodes:
      - name: replay
        plugin: marker_replay            # entry point in group uuomocap.nodes
        params: {file: $(arg markers), speed: $(arg speed)}
        remap: {markers/raw: markers/tracked}
        respawn: {policy: on-failure, max_retries: 3, backoff_s: 0.5}   # or: never | on-failure | always
        on_exit: shutdown                # the graph ends when this node finishes
        required: false                  # a permanent failure of this node ends the graph with an error
        nice: 10                         # lower CPU priority (0-19) for work that can wait for the critical path
        if: $(arg lockstep)              # / unless: ...

Substitutions: ``$(arg NAME)``, ``$(env NAME [DEFAULT])``, ``$(dirname)`` (this file's
folder), ``$(exists PATH)`` and ``$(nonempty TEXT)`` (true/false); innermost first, so they nest. A value
that is exactly one substitution keeps its type (numbers, booleans, lists).

Validation happens before anything is spawned and reports every problem: unknown
plugin, bad parameter (the node's config dataclass), topic nobody publishes,
unknown ack_from node, endpoint collisions, duplicate node names.

Process hygiene: children run in their own process group; each sets
PR_SET_PDEATHSIG(SIGKILL) in its pre-exec hook so it dies with the launcher even
if the launcher is SIGKILLed; shutdown goes in data-flow order (sources first,
so sinks record what is still in flight) with SIGINT, then SIGTERM, then SIGKILL.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

import uuomocap.launch as uuomocap_launch
from uuomocap.nodes.base import Node, Port, PluginError, load_plugin
from uuomocap.nodes.config import ConfigError
from uuomocap.protocol.transport import Endpoints, endpoint_in_use, runtime_root

LAUNCH_DIR = Path(uuomocap_launch.__file__).resolve().parent  # the shipped launch files (package uuomocap.launch)
NODE_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
TOPIC_RE = re.compile(r"^[a-z0-9_\-]+(/[a-z0-9_\-]+)*$")
SUBST_RE = re.compile(r"\$\((\w[\w-]*)((?:\s+[^()$]*)?)\)")
RESPAWN_POLICIES = ("never", "on-failure", "always")
PR_SET_PDEATHSIG = 1


class LaunchError(Exception):
    """A launch file or graph that cannot run; ``problems`` lists every issue found."""

    def __init__(self, problems: list[str] | str):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        super().__init__("; ".join(self.problems))


# ------------------------------------------------------------------------------------------
# Launch file -> GraphSpec
# ------------------------------------------------------------------------------------------


@dataclass
class Respawn:
    policy: str = "never"
    max_retries: int = 3
    backoff_s: float = 0.5
    backoff_max_s: float = 10.0


@dataclass
class NodeSpec:
    name: str
    plugin: str
    params: dict
    remaps: dict[str, str] = field(default_factory=dict)
    respawn: Respawn = field(default_factory=Respawn)
    on_exit: str = "ignore"  # ignore | shutdown
    required: bool = False
    origin: str = ""
    nice: int = 0  # added to the process's niceness at spawn (0-19)


@dataclass
class GraphSpec:
    name: str
    file: str
    nodes: list[NodeSpec]
    transport: dict
    external_topics: list[str]
    args: dict[str, Any]


def parse_cli_args(items: list[str]) -> dict[str, Any]:
    """['speed:=2', 'session:=/x'] -> {'speed': 2, 'session': '/x'} (values parsed as YAML scalars)."""
    out = {}
    for item in items:
        key, sep, value = item.partition(":=")
        if not sep or not key:
            raise LaunchError(f"launch arguments look like key:=value, got {item!r}")
        out[key] = _yaml_scalar(value)
    return out


def _yaml_scalar(text: str) -> Any:
    try:
        return yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError:
        return text


def _to_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return "" if value is None else str(value)


class _Subst:
    def __init__(self, args: dict[str, Any], file: Path, where: str):
        self.args, self.file, self.where = args, file, where

    def one(self, name: str, rest: str) -> Any:
        rest = rest.strip()
        if name == "arg":
            if rest not in self.args:
                raise LaunchError(f"{self.where}: $(arg {rest}) names no declared argument (declared: {', '.join(self.args) or 'none'})")
            return self.args[rest]
        if name == "env":
            var, _, default = rest.partition(" ")
            if var not in os.environ and not default:
                raise LaunchError(f"{self.where}: environment variable {var} is not set")
            return os.environ.get(var, default.strip())
        if name == "dirname":
            return str(self.file.parent)
        if name == "exists":
            return Path(rest).exists()
        if name == "nonempty":  # an optional text argument was given (a camera, a stream URL)
            return bool(rest)
        raise LaunchError(f"{self.where}: unknown substitution $({name} ...) (known: arg, env, dirname, exists, nonempty)")

    def value(self, v: Any) -> Any:
        if isinstance(v, dict):
            return {self.value(k): self.value(x) for k, x in v.items()}
        if isinstance(v, list):
            return [self.value(x) for x in v]
        if not isinstance(v, str) or "$(" not in v:
            return v
        text = v
        while True:
            m = SUBST_RE.search(text)
            if m is None:
                break
            result = self.one(m.group(1), m.group(2))
            if m.start() == 0 and m.end() == len(text):
                return result  # whole value is one substitution: keep its type
            text = text[: m.start()] + _to_text(result) + text[m.end():]
        if "$(" in text:
            raise LaunchError(f"{self.where}: malformed substitution in {v!r}")
        return text


def _truthy(value: Any, where: str) -> bool:
    if isinstance(value, str):
        value = _yaml_scalar(value)
    if not isinstance(value, bool):
        raise LaunchError(f"{where}: condition must be true or false, got {value!r}")
    return value


def _respawn(value: Any, where: str) -> Respawn:
    if value is None or value is False:
        return Respawn()
    if isinstance(value, str):
        value = {"policy": value}
    if not isinstance(value, dict):
        raise LaunchError(f"{where}: respawn must be a policy name or a mapping")
    unknown = set(value) - {"policy", "max_retries", "backoff_s", "backoff_max_s"}
    if unknown:
        raise LaunchError(f"{where}: unknown respawn key {sorted(unknown)[0]!r}")
    r = Respawn(**value)
    if r.policy not in RESPAWN_POLICIES:
        raise LaunchError(f"{where}: respawn policy must be one of {', '.join(RESPAWN_POLICIES)}, got {r.policy!r}")
    if not isinstance(r.max_retries, int) or r.max_retries < 0 or not isinstance(r.backoff_s, (int, float)) or r.backoff_s < 0:
        raise LaunchError(f"{where}: respawn max_retries must be an int >= 0 and backoff_s a number >= 0")
    return r


def resolve_launch_path(path: str | Path) -> Path:
    """A path as given, or a bare name of a shipped launch file ('record_markers')."""
    p = Path(path)
    if p.is_file():
        return p.resolve()
    for cand in (LAUNCH_DIR / p, LAUNCH_DIR / f"{p}.yaml", LAUNCH_DIR / p.name):
        if cand.is_file():
            return cand
    raise LaunchError(f"launch file {str(path)!r} not found (shipped: {', '.join(sorted(f.stem for f in LAUNCH_DIR.glob('*.yaml')))})")


def load_launch(path: str | Path, cli_args: dict[str, Any] | None = None, _depth: int = 0, _strict: bool = True) -> GraphSpec:
    """Read a launch file (and its includes) with arguments substituted."""
    file = resolve_launch_path(path)
    if _depth > 8:
        raise LaunchError(f"{file}: includes nested deeper than 8 (a cycle?)")
    try:
        doc = yaml.safe_load(file.read_text()) or {}
    except yaml.YAMLError as exc:
        raise LaunchError(f"{file}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise LaunchError(f"{file}: a launch file is a mapping with 'nodes'")
    unknown = set(doc) - {"name", "args", "transport", "external_topics", "include", "nodes", "description"}
    if unknown:
        raise LaunchError(f"{file}: unknown top-level key {sorted(unknown)[0]!r}")
    cli_args = dict(cli_args or {})
    declared = doc.get("args") or {}
    if not isinstance(declared, dict):
        raise LaunchError(f"{file}: 'args' must be a mapping")
    if _strict:
        extra = sorted(set(cli_args) - set(declared))
        if extra:
            raise LaunchError(f"{file.name}: unknown argument {extra[0]!r} (declared: {', '.join(declared) or 'none'})")
    args: dict[str, Any] = {}
    for key, decl in declared.items():
        decl = decl if isinstance(decl, dict) else {"default": decl}
        sub = _Subst(args, file, f"{file.name}: argument {key!r}")
        if key in cli_args:
            args[key] = sub.value(cli_args[key])
        elif "default" in decl:
            args[key] = sub.value(decl["default"])
        else:
            hint = f" ({decl['help']})" if decl.get("help") else ""
            raise LaunchError(f"{file.name}: argument {key!r} is required{hint}: pass {key}:=VALUE")
    sub = _Subst(args, file, file.name)
    nodes: list[NodeSpec] = []
    external = list(sub.value(doc.get("external_topics") or []))
    for i, inc in enumerate(doc.get("include") or []):
        where = f"{file.name}: include #{i + 1}"
        if not isinstance(inc, dict) or "file" not in inc:
            raise LaunchError(f"{where}: an include needs 'file'")
        inc = sub.value(inc)
        if not _condition(inc, where):
            continue
        inc_path = Path(inc["file"])
        inc_path = inc_path if inc_path.is_absolute() else file.parent / inc_path
        child = load_launch(inc_path, inc.get("args") or {}, _depth + 1)
        nodes.extend(child.nodes)
        external.extend(child.external_topics)
    for i, raw in enumerate(doc.get("nodes") or []):
        where = f"{file.name}: node #{i + 1}"
        if not isinstance(raw, dict):
            raise LaunchError(f"{where}: a node is a mapping with name and plugin")
        unknown = set(raw) - {"name", "plugin", "params", "remap", "respawn", "on_exit", "required", "if", "unless", "nice"}
        if unknown:
            raise LaunchError(f"{where}: unknown key {sorted(unknown)[0]!r}")
        raw = sub.value(raw)
        if not _condition(raw, where):
            continue
        name, plugin = raw.get("name"), raw.get("plugin")
        if not isinstance(name, str) or not NODE_NAME_RE.match(name):
            raise LaunchError(f"{where}: node name {name!r} must be letters, digits, '_' or '-' (starting with a letter)")
        where = f"{file.name}: node '{name}'"
        if not isinstance(plugin, str):
            raise LaunchError(f"{where}: 'plugin' must name an installed node plugin")
        remaps = raw.get("remap") or {}
        if not isinstance(remaps, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in remaps.items()):
            raise LaunchError(f"{where}: 'remap' must map topic names to topic names")
        on_exit = raw.get("on_exit", "ignore")
        if on_exit not in ("ignore", "shutdown"):
            raise LaunchError(f"{where}: on_exit must be ignore or shutdown, got {on_exit!r}")
        nice = raw.get("nice", 0)
        if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
            raise LaunchError(f"{where}: nice must be an integer 0-19 (lower CPU priority), got {nice!r}")
        nodes.append(NodeSpec(name, plugin, raw.get("params") or {}, remaps, _respawn(raw.get("respawn"), where), on_exit,
                              bool(raw.get("required", False)), str(file), nice))
    transport = sub.value(doc.get("transport") or {"kind": "ipc"})
    return GraphSpec(str(doc.get("name") or file.stem), str(file), nodes, transport, external, args)


def _condition(item: dict, where: str) -> bool:
    ok = True
    if "if" in item:
        ok = ok and _truthy(item.pop("if"), where)
    if "unless" in item:
        ok = ok and not _truthy(item.pop("unless"), where)
    return ok


# ------------------------------------------------------------------------------------------
# Validation
# ------------------------------------------------------------------------------------------


@dataclass
class ValidNode:
    spec: NodeSpec
    cls: type[Node]
    config: Any
    inputs: dict[str, Port]
    outputs: dict[str, str]


@dataclass
class ValidGraph:
    spec: GraphSpec
    nodes: list[ValidNode]
    endpoints: Endpoints | None  # None: ipc in a fresh runtime dir (decided at start)
    expect: dict[str, dict[str, list[str]]]  # publisher node -> {topic: [subscriber nodes]}
    ack_nodes: set[str]
    warnings: list[str]

    def topics(self) -> dict[str, dict[str, list[str]]]:
        """topic -> {'publishers': [...], 'subscribers': [...]} (patterns listed as given)."""
        out: dict[str, dict[str, list[str]]] = {}
        for n in self.nodes:
            for t in n.outputs.values():
                out.setdefault(t, {"publishers": [], "subscribers": []})["publishers"].append(n.spec.name)
            for p in n.inputs.values():
                out.setdefault(p.topic, {"publishers": [], "subscribers": []})["subscribers"].append(n.spec.name)
        return out


def _matches(pattern: Port, topic: str) -> bool:
    if pattern.is_pattern:
        return topic.startswith(pattern.topic.rstrip("*"))
    return pattern.topic == topic


def _endpoints(transport: dict) -> tuple[Endpoints | None, list[str]]:
    kind = transport.get("kind", "ipc")
    if kind == "ipc":
        unknown = set(transport) - {"kind", "dir"}
        if unknown:
            return None, [f"transport: unknown key {sorted(unknown)[0]!r} for ipc"]
        return (Endpoints.ipc(transport["dir"]) if transport.get("dir") else None), []
    if kind == "tcp":
        unknown = set(transport) - {"kind", "host", "frontend_port", "backend_port"}
        if unknown:
            return None, [f"transport: unknown key {sorted(unknown)[0]!r} for tcp"]
        fp, bp = transport.get("frontend_port", 5560), transport.get("backend_port", 5561)
        if not all(isinstance(p, int) and 0 < p < 65536 for p in (fp, bp)):
            return None, ["transport: frontend_port and backend_port must be port numbers"]
        return Endpoints.tcp(str(transport.get("host", "127.0.0.1")), fp, bp), []
    return None, [f"transport: kind must be ipc or tcp, got {kind!r}"]


def validate(spec: GraphSpec) -> ValidGraph:
    """Check the whole graph before spawning; raise LaunchError listing every problem."""
    problems: list[str] = []
    warnings: list[str] = []
    valid: list[ValidNode] = []
    seen: set[str] = set()
    if not spec.nodes:
        problems.append(f"{spec.name}: the graph has no nodes")
    for ns in spec.nodes:
        where = f"node '{ns.name}'"
        if ns.name in seen:
            problems.append(f"{where}: duplicate node name")
            continue
        seen.add(ns.name)
        try:
            cls = load_plugin(ns.plugin)
        except PluginError as exc:
            problems.append(f"{where}: {exc}")
            continue
        except Exception as exc:  # the plugin's import itself failed
            problems.append(f"{where}: plugin '{ns.plugin}' failed to import ({type(exc).__name__}: {exc})")
            continue
        try:
            config = cls.parse_config(ns.params, where)
            inputs, outputs = cls.remapped_ports(config, ns.remaps)
        except ConfigError as exc:
            problems.append(str(exc))
            continue
        except Exception as exc:
            problems.append(f"{where}: {type(exc).__name__}: {exc}")
            continue
        for t in [p.topic for p in inputs.values() if not p.is_pattern] + list(outputs.values()):
            if not TOPIC_RE.match(t):
                problems.append(f"{where}: topic {t!r} is not a lower-case path like 'markers/raw'")
        valid.append(ValidNode(ns, cls, config, inputs, outputs))
    published: dict[str, list[str]] = {}
    for n in valid:
        for t in n.outputs.values():
            published.setdefault(t, []).append(n.spec.name)
    for t, pubs in published.items():
        if len(pubs) > 1:
            warnings.append(f"topic '{t}' has several publishers: {', '.join(pubs)}")
    for n in valid:
        for port, p in n.inputs.items():
            if p.is_pattern or p.optional or p.topic in published or p.topic in spec.external_topics:
                continue
            have = ", ".join(f"{t} ({'/'.join(v)})" for t, v in sorted(published.items())) or "nothing"
            problems.append(
                f"node '{n.spec.name}' subscribes to '{p.topic}' (port {port}) but no node publishes it "
                f"(published: {have}); add a publisher, a remap, or list it under external_topics"
            )
    names = {n.spec.name: n for n in valid}
    ack_nodes: set[str] = set()
    for n in valid:
        for entry in getattr(n.config, "ack_from", []):
            node, _, topic = entry.partition(":")
            if node not in names:
                if node in seen:
                    continue  # reported already
                problems.append(f"node '{n.spec.name}': ack_from names '{node}', which is not a node of this graph")
                continue
            ack_nodes.add(node)
            wanted = [n.spec.remaps.get(topic, topic)] if topic else list(n.outputs.values())
            if not any(_matches(p, t) for p in names[node].inputs.values() for t in wanted):
                what = f"'{topic}'" if topic else f"any of its topics ({', '.join(wanted) or 'none'})"
                problems.append(f"node '{n.spec.name}': ack_from '{entry}' but '{node}' does not subscribe to {what}, so it never acknowledges")
    expect: dict[str, dict[str, list[str]]] = {}
    for n in valid:
        for t in n.outputs.values():
            subs = sorted(m.spec.name for m in valid if m is not n and any(_matches(p, t) for p in m.inputs.values()))
            if subs:
                expect.setdefault(n.spec.name, {})[t] = subs
    endpoints, eproblems = _endpoints(spec.transport)
    problems += eproblems
    if endpoints is not None:
        if endpoints.frontend == endpoints.backend:
            problems.append(f"transport: frontend and backend are the same endpoint {endpoints.frontend}")
        for ep in (endpoints.frontend, endpoints.backend):
            why = endpoint_in_use(ep)
            if why:
                problems.append(f"transport: {why}")
    if problems:
        raise LaunchError(problems)
    return ValidGraph(spec, valid, endpoints, expect, ack_nodes, warnings)


def flow_levels(graph: ValidGraph) -> list[list[str]]:
    """Node names grouped by data-flow depth (sources first); members of cycles share a level."""
    preds: dict[str, set[str]] = {n.spec.name: set() for n in graph.nodes}
    for n in graph.nodes:
        for m in graph.nodes:
            if m is not n and any(_matches(p, t) for p in m.inputs.values() for t in n.outputs.values()):
                preds[m.spec.name].add(n.spec.name)
    # longest path from a source; iterating |V| times bounds it, so cycles just end up deep
    depth = {name: 0 for name in preds}
    for _ in range(len(preds)):
        for name, ps in preds.items():
            depth[name] = min(len(preds), max([depth[p] + 1 for p in ps] + [0]))
    levels: dict[int, list[str]] = {}
    for name in preds:
        levels.setdefault(depth[name], []).append(name)
    return [levels[k] for k in sorted(levels)]


# ------------------------------------------------------------------------------------------
# Running
# ------------------------------------------------------------------------------------------


def _libc_prctl():
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        return libc.prctl
    except OSError:  # not glibc/Linux: no parent-death signal, the process group still applies
        return None


@dataclass
class Child:
    name: str
    argv: list[str]
    respawn: Respawn
    on_exit: str = "ignore"
    required: bool = False
    is_broker: bool = False
    proc: subprocess.Popen | None = None
    retries: int = 0
    incarnation: int = 0
    next_start: float | None = None
    done: bool = False
    exit_codes: list[int] = field(default_factory=list)
    nice: int = 0


class Launcher:
    """Spawn a validated graph, supervise it, shut it down in order."""

    def __init__(self, graph: ValidGraph, *, log_dir: str | Path | None = None, ready_timeout_s: float = 30.0, quiet: bool = False):
        self.graph = graph
        self.name = graph.spec.name
        self.quiet = quiet
        self.ready_timeout_s = ready_timeout_s
        self.runtime_dir = runtime_root() / f"{self.name}-{os.getpid()}"
        self.endpoints = graph.endpoints or Endpoints.ipc(self.runtime_dir)
        self.session = f"{self.name}-{os.getpid()}-{int(time.time())}"
        self.log_dir = Path(log_dir) if log_dir else None
        self.children: dict[str, Child] = {}
        self.pgid: int | None = None
        self._prctl = _libc_prctl()
        self._stop_reason: str | None = None
        self._exit_code = 0

    def say(self, msg: str) -> None:
        if not self.quiet:
            print(f"[launch] {msg}", file=sys.stderr, flush=True)

    # -- children -----------------------------------------------------------------------------
    def _argv(self, vn: ValidNode) -> list[str]:
        ns = vn.spec
        argv = [sys.executable, "-m", "uuomocap.nodes.run", ns.plugin, "--name", ns.name, "--endpoints", str(self.endpoints),
                "--params", json.dumps(ns.params), "--session", self.session, "--ready-timeout", str(self.ready_timeout_s),
                "--expect", json.dumps(self.graph.expect.get(ns.name, {}))]
        for k, v in ns.remaps.items():
            argv += ["--remap", f"{k}={v}"]
        if ns.name in self.graph.ack_nodes:
            argv.append("--ack")
        return argv

    def _preexec(self, parent_pid: int, pgid: int | None, nice: int = 0):
        prctl = self._prctl

        def hook():
            if nice:
                os.nice(nice)
            if prctl is not None:
                prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
            if os.getppid() != parent_pid:  # the launcher died before prctl took effect
                os._exit(1)
            try:
                os.setpgid(0, pgid or 0)
            except OSError:  # the old group is gone: start a new one (the launcher re-reads it)
                os.setpgid(0, 0)
            signal.signal(signal.SIGINT, signal.SIG_DFL)

        return hook

    def _spawn(self, child: Child) -> None:
        argv = list(child.argv)
        if not child.is_broker:
            argv += ["--incarnation", str(child.incarnation)]
        out = None
        if self.log_dir:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_dir / f"{child.name}.log", "ab")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        child.proc = subprocess.Popen(argv, preexec_fn=self._preexec(os.getpid(), self.pgid, child.nice), stdout=out, stderr=out, stdin=subprocess.DEVNULL, env=env, close_fds=True)
        if out:
            out.close()
        try:
            self.pgid = os.getpgid(child.proc.pid)
        except ProcessLookupError:
            pass
        child.next_start = None
        self._write_graph_json()

    def start(self) -> None:
        self.runtime_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        broker_argv = [sys.executable, "-m", "uuomocap.protocol.transport", "--frontend", self.endpoints.frontend, "--backend", self.endpoints.backend]
        self.children["_broker"] = Child("_broker", broker_argv, Respawn("always", 1_000_000, 0.2, 2.0), is_broker=True)
        for vn in self.graph.nodes:
            ns = vn.spec
            self.children[ns.name] = Child(ns.name, self._argv(vn), ns.respawn, ns.on_exit, ns.required, nice=ns.nice)
        for w in self.graph.warnings:
            self.say(f"warning: {w}")
        for child in self.children.values():
            self._spawn(child)
        self.say(f"graph '{self.name}' up: {len(self.graph.nodes)} nodes, broker {self.endpoints}, pgid {self.pgid}, runtime {self.runtime_dir}")

    def _write_graph_json(self) -> None:
        info = {
            "name": self.name,
            "session": self.session,
            "file": self.graph.spec.file,
            "launcher_pid": os.getpid(),
            "pgid": self.pgid,
            "endpoints": {"frontend": self.endpoints.frontend, "backend": self.endpoints.backend},
            "nodes": [
                {
                    "name": vn.spec.name,
                    "plugin": vn.spec.plugin,
                    "pid": self.children[vn.spec.name].proc.pid if vn.spec.name in self.children and self.children[vn.spec.name].proc else None,
                    "incarnation": self.children[vn.spec.name].incarnation if vn.spec.name in self.children else 0,
                    "subscribes": sorted(p.topic for p in vn.inputs.values()),
                    "publishes": sorted(vn.outputs.values()),
                }
                for vn in self.graph.nodes
            ],
            "broker_pid": self.children["_broker"].proc.pid if self.children.get("_broker") and self.children["_broker"].proc else None,
        }
        tmp = self.runtime_dir / "graph.json.tmp"
        tmp.write_text(json.dumps(info, indent=2))
        os.replace(tmp, self.runtime_dir / "graph.json")

    # -- supervision --------------------------------------------------------------------------
    def request_stop(self, reason: str, code: int | None = None) -> None:
        if self._stop_reason is None:
            self._stop_reason = reason
            if code is not None:
                self._exit_code = code

    def supervise(self, timeout_s: float | None = None, on_tick=None) -> int:
        """Run until a shutdown condition (or timeout); then shut down; returns the exit code."""
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        for s in old:
            signal.signal(s, lambda signum, frame: self.request_stop(f"signal {signal.Signals(signum).name}"))
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            while self._stop_reason is None:
                self._tick()
                if on_tick is not None:
                    on_tick(self)
                if deadline is not None and time.monotonic() > deadline:
                    self.request_stop("timeout", 1)
                time.sleep(0.05)
        finally:
            self.shutdown()
            for s, h in old.items():
                signal.signal(s, h)
        return self._exit_code

    def _tick(self) -> None:
        now = time.monotonic()
        for child in self.children.values():
            if child.done:
                continue
            if child.proc is None:
                if child.next_start is not None and now >= child.next_start:
                    child.incarnation += 1
                    self._spawn(child)
                continue
            code = child.proc.poll()
            if code is None:
                continue
            child.exit_codes.append(code)
            child.proc = None
            failed = code != 0
            how = f"exit code {code}" if code >= 0 else f"signal {signal.Signals(-code).name}"
            if not failed and child.on_exit == "shutdown":
                self.say(f"node '{child.name}' finished; shutting the graph down (on_exit: shutdown)")
                child.done = True
                self.request_stop(f"{child.name} finished")
                return
            wants = child.respawn.policy == "always" or (failed and child.respawn.policy == "on-failure")
            if wants and child.retries < child.respawn.max_retries:
                delay = min(child.respawn.backoff_s * (2 ** child.retries), child.respawn.backoff_max_s)
                child.retries += 1
                child.next_start = now + delay
                if not child.is_broker:
                    self.say(f"node '{child.name}' ended ({how}); respawning in {delay:.1f}s ({child.retries}/{child.respawn.max_retries})")
                continue
            child.done = True
            if failed:
                self.say(f"node '{child.name}' failed ({how}); not respawned")
                self._exit_code = 1
                if child.required:
                    self.request_stop(f"required node {child.name} failed", 1)
            else:
                self.say(f"node '{child.name}' finished")
        if all(c.done for c in self.children.values() if not c.is_broker):
            self.request_stop("all nodes ended")

    # -- shutdown -----------------------------------------------------------------------------
    def shutdown(self) -> None:
        self.say(f"shutting down ({self._stop_reason})")
        for level in flow_levels(self.graph):
            procs = [self.children[n] for n in level if self.children[n].proc is not None]
            for c in procs:
                self._signal(c, signal.SIGINT)
            grace = max((next(v.cls.STOP_TIMEOUT_S for v in self.graph.nodes if v.spec.name == c.name) for c in procs), default=0)
            self._wait(procs, grace)
        rest = [c for c in self.children.values() if c.proc is not None and not c.is_broker]
        for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 5.0)):
            alive = [c for c in rest if c.proc is not None and c.proc.poll() is None]
            if not alive:
                break
            self.say(f"sending {sig.name} to {', '.join(c.name for c in alive)}")
            for c in alive:
                self._signal(c, sig)
            self._wait(alive, wait)
        broker = self.children.get("_broker")
        if broker and broker.proc is not None:
            self._signal(broker, signal.SIGTERM)
            self._wait([broker], 3.0)
            if broker.proc is not None and broker.proc.poll() is None:
                self._signal(broker, signal.SIGKILL)
                broker.proc.wait(5)
        if self.pgid:  # anything a node started on its own
            try:
                os.killpg(self.pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        shutil.rmtree(self.runtime_dir, ignore_errors=True)
        for c in self.children.values():
            if c.proc is not None and c.proc.returncode not in (None, 0) and not c.is_broker and c.proc.returncode != -signal.SIGINT:
                code = c.proc.returncode
                self.say(f"node '{c.name}' ended with " + (f"exit code {code}" if code >= 0 else f"signal {signal.Signals(-code).name}")
                         + " during shutdown")
                self._exit_code = self._exit_code or 1
        self.say("graph stopped")

    @staticmethod
    def _signal(child: Child, sig: int) -> None:
        try:
            child.proc.send_signal(sig)
        except ProcessLookupError:
            pass

    @staticmethod
    def _wait(children: list[Child], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        for c in children:
            try:
                c.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass


def launch(path: str | Path, cli_args: dict[str, Any] | None = None, *, log_dir=None, timeout_s=None, quiet=False) -> int:
    """Load, validate, run until done; the exit code of the graph."""
    graph = validate(load_launch(path, cli_args))
    launcher = Launcher(graph, log_dir=log_dir, quiet=quiet)
    launcher.start()
    return launcher.supervise(timeout_s)


def _is_launcher(pid: int) -> bool:
    """The process exists and is a uuomocap launcher (not a reused pid)."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    return b"uuomocap" in cmd


def find_running_graphs() -> list[dict]:
    """graph.json of every graph whose launcher is alive; removes runtime dirs left by killed launchers."""
    out = []
    for f in runtime_root().glob("*/graph.json"):
        try:
            info = json.loads(f.read_text())
            pid = int(info["launcher_pid"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not _is_launcher(pid):
            shutil.rmtree(f.parent, ignore_errors=True)  # its launcher was killed (SIGKILL): stale
            continue
        info["runtime_dir"] = str(f.parent)
        info["_mtime"] = f.stat().st_mtime
        out.append(info)
    return sorted(out, key=lambda i: -i["_mtime"])


def connect_info(graph: str | None = None, endpoints: str | None = None) -> tuple[Endpoints, dict | None]:
    """Endpoints of the graph to talk to: explicit endpoints, a graph name / runtime dir,
    $UUOMOCAP_GRAPH, or the newest running graph. Raises LaunchError when none is found."""
    if endpoints:
        try:
            return Endpoints.parse(endpoints), None
        except ValueError as exc:
            raise LaunchError(str(exc)) from None
    graph = graph or os.environ.get("UUOMOCAP_GRAPH")
    running = find_running_graphs()
    if graph:
        matches = [i for i in running if graph in (i["name"], i["runtime_dir"], Path(i["runtime_dir"]).name)]
        if len(matches) == 1:
            return Endpoints(**matches[0]["endpoints"]), matches[0]
        if len(matches) > 1:
            names = ", ".join(Path(i["runtime_dir"]).name for i in matches)
            raise LaunchError(f"several running graphs are named {graph!r} ({names}): pass the runtime dir name instead")
        names = ", ".join(f"{i['name']} ({Path(i['runtime_dir']).name})" for i in running) or "none"
        raise LaunchError(f"no running graph named {graph!r} (running: {names})")
    if not running:
        raise LaunchError("no running graph found: start one with `uuomocap launch FILE`, or pass --endpoints FRONTEND,BACKEND")
    if len(running) > 1:
        names = ", ".join(Path(i["runtime_dir"]).name for i in running)
        raise LaunchError(f"{len(running)} graphs are running ({names}): choose one with --graph NAME or $UUOMOCAP_GRAPH")
    return Endpoints(**running[0]["endpoints"]), running[0]


def main(argv: list[str] | None = None) -> int:
    """``python -m uuomocap.launcher FILE [key:=value ...]`` (same as ``uuomocap launch``)."""
    from uuomocap.cli import main as cli_main

    return cli_main(["launch", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
