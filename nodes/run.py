"""Run one node plugin as a process: what the launcher spawns.

    python -m uuomocap.nodes.run PLUGIN --name NAME --endpoints FRONT,BACK \
        [--params JSON] [--remap FROM=TO ...] [--expect JSON] [--ack] [--session ID]

Exit codes: 0 finished or stopped, 1 the node failed, 2 bad plugin / parameters.
"""

from __future__ import annotations

import argparse
import json
import sys

from uuomocap.protocol.transport import Endpoints

from .base import ConfigError, PluginError, Runtime, load_plugin


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m uuomocap.nodes.run", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("plugin", help="entry point name in group uuomocap.nodes")
    p.add_argument("--name", required=True, help="node name (unique in the graph)")
    p.add_argument("--endpoints", required=True, help="broker endpoints FRONTEND,BACKEND")
    p.add_argument("--params", default="{}", help="node parameters as a JSON object")
    p.add_argument("--remap", action="append", default=[], metavar="FROM=TO", help="topic remap (repeatable)")
    p.add_argument("--expect", default="{}", help="JSON {topic: [subscriber nodes]} to wait for before publishing")
    p.add_argument("--ack", action="store_true", help="publish ack/<name> after each handled message (lockstep)")
    p.add_argument("--session", default="", help="session / graph id stamped on every message")
    p.add_argument("--incarnation", type=int, default=0, help="respawn count (set by the launcher)")
    p.add_argument("--ready-timeout", type=float, default=30.0, help="seconds to wait for declared subscribers")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cls = load_plugin(args.plugin)
        params = json.loads(args.params)
        remaps = dict(r.split("=", 1) for r in args.remap)
        config = cls.parse_config(params, f"node '{args.name}'")
        runtime = Runtime(
            endpoints=Endpoints.parse(args.endpoints),
            session=args.session,
            remaps=remaps,
            expect={k: list(v) for k, v in json.loads(args.expect).items()},
            ack=args.ack,
            incarnation=args.incarnation,
            ready_timeout_s=args.ready_timeout,
            plugin=args.plugin,
        )
    except (PluginError, ConfigError, ValueError) as exc:
        print(f"uuomocap node {args.name}: error: {exc}", file=sys.stderr)
        return 2
    return cls(args.name, config, runtime).run()


if __name__ == "__main__":
    sys.exit(main())
