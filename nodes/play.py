"""play: republish a recording (every recorded topic, or ``topics``) with its original timing.

Pacing follows the recorded publish times (``speed`` x), so the interleaving of
topics is reproduced (capture stamps are republished as recorded, also when
looping); ``lockstep`` instead sends each message once the
``ack_from`` nodes have credited the previous ones. Messages are re-validated
on the way out; health/control topics (heartbeat/, diag/, log/, ack/, ready/)
are not replayed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from uuomocap.protocol.envelope import DecodeError
from uuomocap.protocol.recording import iter_recording, recording_info

from .base import Node, Pacer

NOT_REPLAYED = ("heartbeat/", "diag/", "log/", "ack/", "ready/")


@dataclass(frozen=True)
class PlayConfig:
    file: str  # .mcap recording
    topics: list[str] = field(default_factory=list)  # [] = every recorded data topic
    speed: float = 1.0
    loop: bool = False
    lockstep: bool = False
    window: int = 1
    ack_from: list[str] = field(default_factory=list)
    ack_timeout_s: float = 30.0

    def __post_init__(self):
        if not Path(self.file).is_file():
            raise ValueError(f"parameter 'file': no such recording {self.file!r}")
        if not self.speed > 0 or self.window < 1:
            raise ValueError("speed > 0 and window >= 1 are required")
        if self.lockstep and not self.ack_from:
            raise ValueError("lockstep needs ack_from")


def recorded_topics(config: PlayConfig) -> list[str]:
    topics = [t for t in recording_info(config.file).topics if not t.startswith(NOT_REPLAYED)]
    return [t for t in topics if t in config.topics] if config.topics else topics


class Play(Node):
    Config = PlayConfig

    @classmethod
    def ports(cls, config: PlayConfig):
        return {}, {t: t for t in recorded_topics(config)}

    def setup(self) -> None:
        self.pacer = Pacer(self.config.speed)
        self.cycle, self.messages = 0, None
        if self.config.ack_from:
            self.track_acks(self.ack_sources(self.config))

    def step(self) -> bool:
        c = self.config
        if self.messages is None:
            self.messages = iter_recording(c.file, topics=list(self.outputs))
            self.span, self.first = 0, None
        rec = next(self.messages, None)
        if rec is None:
            if c.loop and self.first is not None:
                self.cycle += self.span + 1
                self.messages = None
                return True
            for port in self.outputs:
                self.end_stream(port)
            for port, topic in self.outputs.items():  # wait until the credit nodes handled every end
                consumers = [e for e in c.ack_from if ":" not in e and self.acked(e, topic) is not None]
                if consumers:
                    self.wait_for_credit(port, 0, 0, consumers, 1, c.ack_timeout_s, require_eos=True)
            return False
        try:
            env = rec.decode()
        except DecodeError as exc:
            self.count("undecodable")
            self.log.warning("skipping recorded message on %s: %s", rec.topic, exc)
            return True
        if env.type in ("EndOfStream",):
            return True
        self.first = rec.publish_time_ns if self.first is None else self.first
        self.span = max(self.span, rec.publish_time_ns - self.first)
        if c.lockstep:
            seq = self._pub.next_seq(env.topic)
            self.wait_for_credit(env.topic, seq, env.stamp_ns, c.ack_from, c.window, c.ack_timeout_s)
        else:
            self.wait_ready()  # every output's subscribers before the clock starts (no start-up burst)
            if not self.sleep_until(self.pacer.due_ns(rec.publish_time_ns - self.first + self.cycle)):
                return False
        self.publish(env.topic, env.message, env.stamp_ns)
        self.count("played")
        return True
