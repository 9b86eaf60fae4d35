"""``uuomocap launch FILE.yaml [key:=value ...]``: validate and run a graph (see uuomocap.launcher)."""

from __future__ import annotations

from uuomocap.commands import UserError, add_json_flag, emit


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "launch",
        help="run a graph from a YAML launch file",
        description=(
            "Validate a launch file (plugins installed, parameters, every subscribed topic published, "
            "endpoints free) and run its nodes as supervised processes until the graph finishes or "
            "you press Ctrl-C. FILE is a path or the name of a shipped launch file "
            "(record_markers, replay_session, offline_solve). Arguments: key:=value."
        ),
    )
    p.add_argument("file", help="launch file path or shipped name")
    p.add_argument("args", nargs="*", metavar="key:=value", help="launch arguments")
    p.add_argument("--check", action="store_true", help="only validate and print the graph; spawn nothing")
    p.add_argument("--log-dir", help="write each node's output to DIR/<node>.log instead of this terminal")
    p.add_argument("--timeout", type=float, help="stop the graph after this many seconds (exit code 1)")
    p.add_argument("--ready-timeout", type=float, default=30.0, help="seconds a publisher waits for its declared subscribers")
    add_json_flag(p)
    p.set_defaults(func=run)


def describe(graph) -> dict:
    from uuomocap.launcher import flow_levels

    return {
        "name": graph.spec.name,
        "file": graph.spec.file,
        "args": graph.spec.args,
        "transport": str(graph.endpoints) if graph.endpoints else "ipc (fresh runtime dir)",
        "nodes": [
            {
                "name": n.spec.name,
                "plugin": n.spec.plugin,
                "subscribes": {k: p.topic for k, p in n.inputs.items()},
                "publishes": n.outputs,
                "respawn": n.spec.respawn.policy,
                "waits_for": graph.expect.get(n.spec.name, {}),
                "acks": n.spec.name in graph.ack_nodes,
            }
            for n in graph.nodes
        ],
        "topics": graph.topics(),
        "shutdown_order": flow_levels(graph),
        "warnings": graph.warnings,
    }


def _text(d: dict) -> str:
    lines = [f"graph {d['name']}  ({d['file']})", f"  transport: {d['transport']}"]
    for n in d["nodes"]:
        lines.append(f"  node {n['name']} [{n['plugin']}] respawn={n['respawn']}{' acks' if n['acks'] else ''}")
        for port, t in n["subscribes"].items():
            lines.append(f"      <- {t}  ({port})")
        for port, t in n["publishes"].items():
            waits = n["waits_for"].get(t)
            lines.append(f"      -> {t}  ({port})" + (f"  waits for {', '.join(waits)}" if waits else ""))
    lines.append("  shutdown order: " + " -> ".join("+".join(level) for level in d["shutdown_order"]))
    lines += [f"  warning: {w}" for w in d["warnings"]]
    return "\n".join(lines)


def run(args) -> int:
    from uuomocap.launcher import LaunchError, Launcher, load_launch, parse_cli_args, validate

    try:
        graph = validate(load_launch(args.file, parse_cli_args(args.args)))
    except LaunchError as exc:
        if len(exc.problems) == 1:
            raise UserError(exc.problems[0]) from None
        raise UserError(f"{len(exc.problems)} problems: " + " | ".join(exc.problems)) from None
    if args.check:
        d = describe(graph)
        emit(args, d, _text(d))
        return 0
    launcher = Launcher(graph, log_dir=args.log_dir, ready_timeout_s=args.ready_timeout)
    launcher.start()
    code = launcher.supervise(args.timeout)
    if args.json:
        emit(args, {"graph": graph.spec.name, "exit_code": code, "nodes": {n: c.exit_codes for n, c in launcher.children.items()}})
    return code
