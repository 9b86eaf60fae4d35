"""relay: forward one topic to another name, optionally throttled by capture time.

Useful to bridge a live source into a graph that expects another topic name, to
feed a slow consumer a decimated stream (``throttle_hz``), or to insert a
process boundary when testing respawn. Messages are forwarded unchanged with
their capture stamps; the relay's own sequence numbers start a new stream.
"""

from __future__ import annotations

from dataclasses import dataclass

from .base import Node, Port


@dataclass(frozen=True)
class RelayConfig:
    input: str
    output: str
    throttle_hz: float = 0.0  # 0 = forward every message

    def __post_init__(self):
        if self.input == self.output:
            raise ValueError("input and output must be different topics")
        if self.throttle_hz < 0:
            raise ValueError("throttle_hz must be >= 0")


class Relay(Node):
    Config = RelayConfig

    @classmethod
    def ports(cls, config: RelayConfig):
        return {"input": Port(config.input)}, {"output": config.output}

    def setup(self) -> None:
        self.min_gap_ns = int(1e9 / self.config.throttle_hz) if self.config.throttle_hz else 0
        self.last_stamp: int | None = None

    def on_input(self, msg, env) -> None:
        if self.min_gap_ns and self.last_stamp is not None and env.stamp_ns - self.last_stamp < self.min_gap_ns:
            self.count("throttled")
            return
        self.last_stamp = env.stamp_ns
        self.publish("output", msg, env.stamp_ns)

    def on_eos(self, port, env) -> None:
        self.end_stream("output")
