"""``uuomocap record`` and ``uuomocap play``: the recorder and play nodes, run in this process.

Both join a running graph (found like `uuomocap topic`), so they are exactly the
code the launcher runs; ``record`` writes MCAP (+ the solved npz), ``play``
republishes a recording with its timing.
"""

from __future__ import annotations

import threading

from uuomocap.commands import UserError, add_json_flag, emit

from .topic import _add_graph_flags, connect


def register(subparsers) -> None:
    p = subparsers.add_parser("record", help="record topics of a running graph to MCAP",
                              description=("Record topics of a running graph to an MCAP file (crash-safe, chunked) until "
                                           "Ctrl-C or --duration; solved frames (body/solved) are also exported as npz."))
    _add_graph_flags(p)
    p.add_argument("--out", required=True, help="MCAP file to write (.mcap)")
    p.add_argument("--topics", nargs="+", default=["*"], help="topics or prefixes ('a/'); default '*' = all")
    p.add_argument("--duration", type=float, help="stop after S seconds")
    p.add_argument("--compression", choices=("none", "lz4", "zstd"), default="none")
    add_json_flag(p)
    p.set_defaults(func=cmd_record)

    p = subparsers.add_parser("play", help="republish an MCAP recording into a running graph",
                              description="Publish the messages of FILE.mcap into a running graph with their recorded timing.")
    _add_graph_flags(p)
    p.add_argument("file", help="MCAP recording")
    p.add_argument("--topics", nargs="+", default=[], help="only these topics (default: every recorded data topic)")
    p.add_argument("--speed", type=float, default=1.0, help="x real time")
    p.add_argument("--loop", action="store_true")
    add_json_flag(p)
    p.set_defaults(func=cmd_play)


def _subscribers_in_graph(info: dict | None, topics) -> dict[str, list[str]]:
    """{topic: nodes of the running graph that subscribe to it} from its graph.json."""
    from uuomocap.nodes.base import Port

    out = {}
    for t in topics:
        subs = []
        for n in (info or {}).get("nodes", []):
            ports = [Port(p) for p in n.get("subscribes", [])]
            if any(p.topic.rstrip("*") == t[: len(p.topic.rstrip("*"))] if p.is_pattern else p.topic == t for p in ports):
                subs.append(n["name"])
        if subs:
            out[t] = subs
    return out


def _run_node(cls, name: str, params: dict, args, duration: float | None = None):
    from uuomocap.nodes.base import Runtime
    from uuomocap.nodes.config import ConfigError

    endpoints, info = connect(args)
    try:
        config = cls.parse_config(params, name)
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    _, outputs = cls.ports(config)
    # like a launched node, wait until the graph's subscribers of our topics are connected
    expect = _subscribers_in_graph(info, outputs.values())
    node = cls(name, config, Runtime(endpoints, session=(info or {}).get("session", ""), plugin=name, expect=expect, ready_timeout_s=10.0))
    if duration:
        node.DRAIN_ON_STOP_S = 0.0  # a timed recording of a live graph ends at the deadline
    timer = threading.Timer(duration, node.request_stop) if duration else None
    if timer:
        timer.daemon = True
        timer.start()
    code = node.run()
    if timer:
        timer.cancel()
    return node, code


def cmd_record(args) -> int:
    import os

    from uuomocap.nodes.recorder import Recorder

    params = {"out": args.out, "topics": args.topics, "compression": args.compression}
    node, code = _run_node(Recorder, f"record-{os.getpid()}", params, args, args.duration)
    messages = node.writer.messages if hasattr(node, "writer") else 0
    emit(args, {"out": args.out, "messages": messages, "exit_code": code}, f"recorded {messages} messages to {args.out}")
    return code


def cmd_play(args) -> int:
    import os

    from uuomocap.nodes.play import Play

    params = {"file": args.file, "topics": args.topics, "speed": args.speed, "loop": args.loop}
    node, code = _run_node(Play, f"play-{os.getpid()}", params, args)
    played = node.counters.get("played", 0)
    emit(args, {"file": args.file, "played": played, "exit_code": code}, f"played {played} messages from {args.file}")
    return code
