"""recorder: write chosen topics to MCAP (keep-all queue); export the solved topic as OUT.npz.

Crash-safe: a chunk is closed and flushed at least every ``flush_interval_s``
(also when no new messages arrive), so after a SIGKILL the file reads up to the
last flushed chunk. On a clean stop the node first drains what is still in
flight, then finishes the MCAP summary and writes ``export_npz`` (default: the
.mcap path with .npz) from the ``solved_topic`` frames, refined ones preferred.
A respawned recorder writes ``<out>.respawn<N>.mcap`` and never overwrites the
file of its previous incarnation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from uuomocap.protocol.messages import SolvedFrame
from uuomocap.protocol.recording import RecordingWriter, export_solved_npz

from .base import Node, Port


@dataclass(frozen=True)
class RecorderConfig:
    out: str  # .mcap path
    topics: list[str] = field(default_factory=lambda: ["*"])  # exact topics or prefixes 'a/' ; '*' = all
    exclude: list[str] = field(default_factory=lambda: ["ack/", "ready/"])  # prefixes never recorded
    chunk_kib: int = 512
    flush_interval_s: float = 0.5
    compression: Literal["none", "lz4", "zstd"] = "none"
    export_npz: str = ""  # '' = <out>.npz when solved frames were recorded; 'none' = never
    solved_topic: str = "body/solved"
    method: str = "stream"  # written to OUT.npz 'method'

    def __post_init__(self):
        if not self.out.endswith(".mcap"):
            raise ValueError(f"parameter 'out' must end in .mcap, got {self.out!r}")
        if not self.topics:
            raise ValueError("parameter 'topics' must name at least one topic")
        if self.flush_interval_s <= 0 or self.chunk_kib < 1:
            raise ValueError("flush_interval_s > 0 and chunk_kib >= 1 are required")


class Recorder(Node):
    Config = RecorderConfig
    DRAIN_ON_STOP_S = 0.5
    STOP_TIMEOUT_S = 60  # finishing a long recording and its npz export takes a while

    @classmethod
    def ports(cls, config: RecorderConfig):
        return {t: Port(t, optional=True) for t in config.topics}, {}

    def setup(self) -> None:
        c = self.config
        out = Path(c.out)
        if self.runtime.incarnation:
            out = out.with_name(f"{out.stem}.respawn{self.runtime.incarnation}.mcap")
        self.out = out
        self.timer_s = c.flush_interval_s
        self.writer = RecordingWriter(
            out,
            chunk_size=c.chunk_kib * 1024,
            flush_interval_s=c.flush_interval_s,
            compression=c.compression,
            metadata={"recorder": self.name, "session": self.runtime.session, "topics": ",".join(c.topics)},
        )
        self.solved: list[SolvedFrame] = []
        self.unflushed = 0
        self.log.info("recording %s -> %s", ", ".join(c.topics), out)

    def on_message(self, port, msg, env) -> None:
        if env.topic.startswith(tuple(self.config.exclude)):
            return
        self.writer.write(env)
        self.unflushed += 1
        self.count("recorded")
        if env.topic == self.config.solved_topic and isinstance(msg, SolvedFrame):
            self.solved.append(msg)

    def on_eos(self, port, env) -> None:
        self.on_message(port, env.message, env)

    def on_timer(self) -> None:
        if self.unflushed:
            self.writer.flush()
            self.unflushed = 0

    def teardown(self) -> None:
        if not hasattr(self, "writer"):
            return
        self.writer.close()
        self.log.info("closed %s: %d messages", self.out, self.writer.messages)
        c = self.config
        if self.solved and c.export_npz != "none":
            npz = Path(c.export_npz) if c.export_npz else self.out.with_suffix(".npz")
            info = export_solved_npz(self.solved, npz, method=c.method)
            self.log.info("exported %d solved frames (%d refined, %d of them revised) -> %s", info["frames"], info["refined"],
                          info["revised"], npz)
