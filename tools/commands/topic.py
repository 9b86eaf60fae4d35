"""Introspection of a running graph: ``uuomocap topic list | echo | hz`` and ``uuomocap graph``.

The tools join the graph's broker as plain subscribers (they never slow it
down: nobody waits for them). The graph is found from --endpoints, --graph
NAME, $UUOMOCAP_GRAPH, or the only running launch (several running: say which).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit
from uuomocap.protocol.messages import CONTROL_TYPES

HEALTH_PREFIXES = ("heartbeat/", "diag/", "log/", "ack/", "ready/")


def _add_graph_flags(p) -> None:
    p.add_argument("--graph", help="name or runtime dir of a running graph (default: the newest)")
    p.add_argument("--endpoints", help="broker endpoints FRONTEND,BACKEND (instead of --graph)")


def connect(args):
    from uuomocap.launcher import LaunchError, connect_info

    try:
        return connect_info(args.graph, args.endpoints)
    except LaunchError as exc:
        raise UserError(str(exc)) from None


def _subscriber(args, patterns: list[str]):
    from uuomocap.protocol.transport import Subscriber

    endpoints, info = connect(args)
    sub = Subscriber(endpoints.backend)
    for p in patterns:
        sub.subscribe(p)
    return sub, info


def register(subparsers) -> None:
    topic = subparsers.add_parser("topic", help="list, echo and measure topics of a running graph",
                                  description="Look at the topics of a running graph (see `uuomocap launch`).")
    tsub = topic.add_subparsers(dest="topic_cmd", metavar="CMD")
    topic.set_defaults(func=lambda a: (topic.print_help(sys.stderr), 2)[1])

    p = tsub.add_parser("list", help="topics seen on the broker, with types, publishers and rates",
                        description="Listen for --duration seconds and list every topic seen (plus topics the launch file declares).")
    _add_graph_flags(p)
    p.add_argument("--duration", type=float, default=2.0, help="seconds to listen (default 2)")
    p.add_argument("--all", action="store_true", help="include health/control topics (heartbeat/, diag/, log/, ack/, ready/)")
    add_json_flag(p)
    p.set_defaults(func=cmd_list)

    p = tsub.add_parser("echo", help="print the messages of a topic",
                        description="Print messages of TOPIC (header, scalar fields, array summaries) until --count or --duration.")
    _add_graph_flags(p)
    p.add_argument("topic", help="topic name, or a prefix ending in '/'")
    p.add_argument("--count", type=int, help="stop after N messages")
    p.add_argument("--duration", type=float, help="stop after S seconds")
    p.add_argument("--arrays", action="store_true", help="print array values, not just dtype and shape")
    add_json_flag(p)
    p.set_defaults(func=cmd_echo)

    p = tsub.add_parser("hz", help="rate, jitter, drops and latency of a topic",
                        description=("Measure TOPIC: rate from capture stamps and from publish times, drops from "
                                     "sequence numbers (gaps; messages sent before we joined are reported apart), "
                                     "publish->receive latency."))
    _add_graph_flags(p)
    p.add_argument("topic")
    p.add_argument("--duration", type=float, default=5.0,
                   help="seconds to measure, counted from the first message (default 5); a topic that sends nothing "
                        f"ends the command after DURATION + {HZ_JOIN_WAIT_S:.0f} s")
    p.add_argument("--window", type=float, default=1.0, help="print a line every WINDOW seconds (text mode)")
    add_json_flag(p)
    p.set_defaults(func=cmd_hz)

    p = subparsers.add_parser("graph", help="nodes, topics, publishers/subscribers and health of a running graph",
                              description=("Show the running graph: nodes (plugin, pid, state from heartbeats, counters "
                                           "from diagnostics), topics with publishers and subscribers. "
                                           "--plugins lists installed node plugins and their parameters instead."))
    _add_graph_flags(p)
    p.add_argument("--duration", type=float, default=2.5, help="seconds to listen for heartbeats/diagnostics")
    p.add_argument("--plugins", action="store_true", help="list installed node plugins and their parameters")
    add_json_flag(p)
    p.set_defaults(func=cmd_graph)


def _listen(sub, duration: float, on_env, stop=lambda: False) -> None:
    end = time.monotonic() + duration
    while not stop():
        left = end - time.monotonic()
        if left <= 0:
            break
        for env in sub.recv(int(min(left, 0.1) * 1000)):
            on_env(env)


def cmd_list(args) -> int:
    sub, info = _subscriber(args, ["*"])
    seen: dict[str, dict] = {}

    def on_env(env):
        t = seen.setdefault(env.topic, {"types": set(), "publishers": set(), "count": 0})
        if env.type not in CONTROL_TYPES or env.topic.startswith(HEALTH_PREFIXES):
            t["types"].add(env.type)
        t["publishers"].add(env.source)
        t["count"] += 1

    try:
        _listen(sub, args.duration, on_env)
    finally:
        sub.close()
    declared = {}
    for n in (info or {}).get("nodes", []):
        for t in n["publishes"]:
            declared.setdefault(t, set()).add(n["name"])
    rows = []
    for topic in sorted(set(seen) | set(declared)):
        if not args.all and topic.startswith(HEALTH_PREFIXES):
            continue
        s = seen.get(topic, {"types": set(), "publishers": set(), "count": 0})
        rows.append({
            "topic": topic,
            "types": sorted(s["types"]),
            "publishers": sorted(s["publishers"] | declared.get(topic, set())),
            "messages": s["count"],
            "rate_hz": round(s["count"] / args.duration, 2),
        })
    text = "\n".join(f"{r['topic']:<28} {','.join(r['types']) or '-':<14} {r['rate_hz']:>8.1f} Hz  from {', '.join(r['publishers']) or '?'}" for r in rows)
    emit(args, {"graph": (info or {}).get("name"), "listened_s": args.duration, "topics": rows}, text or "(no topics seen)")
    return 0


def message_dict(env, arrays: bool = False) -> dict:
    msg = env.message
    out = {"topic": env.topic, "type": env.type, "seq": env.seq, "stamp_ns": env.stamp_ns, "source": env.source}
    out.update(msg.scalars())
    for k, a in msg.arrays().items():
        out[k] = a.tolist() if arrays else f"{a.dtype} {tuple(a.shape)}"
    return out


def cmd_echo(args) -> int:
    pattern = args.topic
    sub, _ = _subscriber(args, [pattern])
    n = 0

    def on_env(env):
        nonlocal n
        n += 1
        d = message_dict(env, args.arrays)
        if args.json:
            print(json.dumps(d, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o)), flush=True)
        else:
            print("---\n" + "\n".join(f"{k}: {v}" for k, v in d.items()), flush=True)

    try:
        _listen(sub, args.duration if args.duration else 1e9, on_env, stop=lambda: args.count is not None and n >= args.count)
    except KeyboardInterrupt:
        pass
    finally:
        sub.close()
    return 0 if n else 1


def hz_summary(samples: list[tuple[int, int, int]], stats) -> dict:
    """samples: (stamp_ns, publish_ns, receive_ns) per message."""
    n = len(samples)
    out = {"messages": n, "gaps": stats.gaps, "missed_at_join": stats.missed_at_join, "out_of_order": stats.out_of_order}
    if n >= 2:
        st, pt, rt = (np.array(c, np.float64) for c in zip(*samples))
        span_st, span_pt = (st[-1] - st[0]) / 1e9, (pt[-1] - pt[0]) / 1e9
        out["rate_capture_hz"] = (n - 1) / span_st if span_st > 0 else None
        out["rate_publish_hz"] = (n - 1) / span_pt if span_pt > 0 else None
        dt = np.diff(pt) / 1e6
        out["interval_ms"] = {"mean": float(dt.mean()), "std": float(dt.std()), "max": float(dt.max())}
        lat = (rt - pt) / 1e6
        out["latency_ms"] = {k: float(np.percentile(lat, q)) for k, q in (("p50", 50), ("p95", 95), ("p99", 99))} | {"max": float(lat.max())}
    return out


HZ_JOIN_WAIT_S = 5.0  # how long `topic hz` waits for a first message beyond --duration


def _hz_line(topic: str, s: dict) -> str:
    if s["messages"] < 2:
        return f"{topic}: {s['messages']} messages"
    rc = s.get("rate_capture_hz") or float("nan")
    rp = s.get("rate_publish_hz") or float("nan")
    return (f"{topic}: {rp:.2f} Hz published, {rc:.2f} Hz capture | jitter {s['interval_ms']['std']:.2f} ms | "
            f"drops {s['gaps']} (missed before join {s['missed_at_join']}) | latency p50 {s['latency_ms']['p50']:.2f} ms")


def cmd_hz(args) -> int:
    sub, _ = _subscriber(args, [args.topic])
    samples: list[tuple[int, int, int]] = []
    next_print = time.monotonic() + args.window
    # the window opens at the first message: a subscription takes a while to reach the publishers
    # (on a loaded machine over 1.5 s, which left a 1.5 s measurement empty)
    end, give_up = None, time.monotonic() + args.duration + HZ_JOIN_WAIT_S
    try:
        while time.monotonic() < (end if end is not None else give_up):
            for env in sub.recv(50):
                if env.seq >= 0:
                    if end is None:
                        end = time.monotonic() + args.duration
                    samples.append((env.stamp_ns, env.publish_ns, time.monotonic_ns()))
            if not args.json and time.monotonic() >= next_print:
                next_print += args.window
                print(_hz_line(args.topic, hz_summary(samples, sub.stats[args.topic])), flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sub.close()
    summary = hz_summary(samples, sub.stats[args.topic])
    emit(args, {"topic": args.topic, **summary}, _hz_line(args.topic, summary))
    return 0 if samples else 1


def _plugins(args) -> int:
    from uuomocap.nodes.base import discover_plugins, load_plugin
    from uuomocap.nodes.config import config_help

    rows = []
    for name, ep in sorted(discover_plugins().items()):
        try:
            cls = load_plugin(name)
            rows.append({"plugin": name, "class": ep.value, "params": config_help(cls.Config),
                         "subscribes": {k: getattr(v, "topic", v) for k, v in cls.SUBSCRIBES.items()}, "publishes": dict(cls.PUBLISHES)})
        except Exception as exc:
            rows.append({"plugin": name, "class": ep.value, "error": f"{type(exc).__name__}: {exc}"})
    lines = []
    for r in rows:
        lines.append(f"{r['plugin']}  ({r['class']})" + (f"  ERROR {r['error']}" if "error" in r else ""))
        for prm in r.get("params", []):
            lines.append(f"    {prm['name']}: {prm['type']} = {prm['default']!r}")
    emit(args, {"plugins": rows}, "\n".join(lines))
    return 0


def cmd_graph(args) -> int:
    if args.plugins:
        return _plugins(args)
    sub, info = _subscriber(args, ["heartbeat/", "diag/"])
    beats: dict[str, tuple[float, object]] = {}
    diags: dict[str, object] = {}

    def on_env(env):
        if env.type == "Heartbeat":
            beats[env.message.node] = (time.monotonic(), env.message)
        elif env.type == "Diagnostics":
            diags[env.message.node] = env.message

    try:
        _listen(sub, args.duration, on_env)
    finally:
        sub.close()
    nodes = []
    declared = {n["name"]: n for n in (info or {}).get("nodes", [])}
    for name in sorted(set(declared) | set(beats)):
        d, hb, dg = declared.get(name, {}), beats.get(name, (None, None))[1], diags.get(name)
        topics = dg.topics if dg else {}
        nodes.append({
            "name": name,
            "plugin": d.get("plugin") or (hb.plugin if hb else "?"),
            "pid": hb.pid if hb else d.get("pid"),
            "state": hb.state if hb else "no heartbeat",
            "uptime_s": round(hb.uptime_s, 1) if hb else None,
            "incarnation": hb.incarnation if hb else d.get("incarnation", 0),
            "publishes": hb.publishes if hb else d.get("publishes", []),
            "subscribes": hb.subscribes if hb else d.get("subscribes", []),
            "handled": (dg.counters.get("handled", 0) if dg else None),
            "rejected": (dg.counters.get("rejected", 0) if dg else None),
            "handler_errors": (dg.counters.get("handler_errors", 0) if dg else None),
            "gaps": sum(t.get("gaps", 0) for t in topics.values()) if dg else None,
        })
    topics: dict[str, dict] = {}
    for n in nodes:
        for t in n["publishes"]:
            topics.setdefault(t, {"publishers": [], "subscribers": []})["publishers"].append(n["name"])
        for t in n["subscribes"]:
            topics.setdefault(t, {"publishers": [], "subscribers": []})["subscribers"].append(n["name"])
    lines = [f"graph {(info or {}).get('name', '?')}  launcher pid {(info or {}).get('launcher_pid', '?')}  broker {(info or {}).get('endpoints', {}).get('backend', args.endpoints)}"]
    lines.append(f"  {'node':<14}{'plugin':<15}{'pid':>7}  {'state':<13}{'up s':>7}{'resp':>5}{'handled':>9}{'rejected':>9}{'errors':>7}{'gaps':>6}")
    for n in nodes:
        fmt = lambda v: "-" if v is None else str(v)  # noqa: E731
        lines.append(f"  {n['name']:<14}{n['plugin']:<15}{fmt(n['pid']):>7}  {n['state']:<13}{fmt(n['uptime_s']):>7}{n['incarnation']:>5}"
                     f"{fmt(n['handled']):>9}{fmt(n['rejected']):>9}{fmt(n['handler_errors']):>7}{fmt(n['gaps']):>6}")
    for t, v in sorted(topics.items()):
        lines.append(f"  {t:<28} {', '.join(v['publishers']) or '(external)'} -> {', '.join(v['subscribers']) or '(nobody)'}")
    emit(args, {"graph": (info or {}).get("name"), "nodes": nodes, "topics": topics}, "\n".join(lines))
    return 0
