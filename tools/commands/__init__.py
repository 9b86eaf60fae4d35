"""CLI verbs, one module per verb group, discovered by ``uuomocap.cli``.

Shared helpers for verbs live here so every verb behaves the same:
``UserError`` for one-line errors, ``emit`` for text-or-JSON output.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from typing import Any, Iterator

import numpy as np


class UserError(Exception):
    """A mistake the user can fix (bad path, bad file, bad option): printed as one line."""


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def bench_progress(args: Any, total: int, desc: str):
    """A benchmark's per-session progress bar (tqdm), or one that draws nothing under ``--quiet`` or
    ``--json`` to stdout (the bar would share the terminal with the JSON)."""
    if getattr(args, "quiet", False) or getattr(args, "json", None) == "-":
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="session", desc=desc)


def emit(args: Any, data: dict, text: str | None = None) -> None:
    """Print ``data`` as JSON when ``--json`` was given, else ``text`` (or key: value lines)."""
    if getattr(args, "json", False):
        json.dump(_jsonable(data), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return
    if text is None:
        text = "\n".join(f"{k}: {v}" for k, v in data.items())
    print(text)


def emit_bench(args: Any, data: dict, text: str) -> None:
    """A benchmark's ``--json [FILE]``: JSON on stdout for ``--json`` alone ('-'), else ``text``,
    and the JSON also written to FILE when one was named."""
    if getattr(args, "json", None) == "-":
        json.dump(_jsonable(data), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return
    print(text)
    if getattr(args, "json", None):
        from pathlib import Path

        Path(args.json).write_text(json.dumps(_jsonable(data), indent=2) + "\n")


def add_json_flag(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON instead of text")


def add_threads_flag(parser) -> None:
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads for this command (default: OMP_NUM_THREADS when set, else every usable core; "
                             "uuo-window and a graph's nodes use one each, as they share the cores live)")


def solo_thread_count(requested: int | None) -> int:
    """Threads for a command that has the machine to itself: ``requested`` (--threads), else the
    user's OMP_NUM_THREADS, else every core this process may run on."""
    from uuomocap import THREADS_FROM_ENVIRONMENT

    if requested is not None:
        if requested < 1:
            raise UserError(f"--threads must be at least 1, got {requested}")
        return requested
    if THREADS_FROM_ENVIRONMENT:
        try:
            return max(1, int(os.environ["OMP_NUM_THREADS"]))
        except ValueError:
            raise UserError(f"OMP_NUM_THREADS must be a whole number, got {os.environ['OMP_NUM_THREADS']!r}") from None
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[int]:
    """Run the block with ``count`` torch intra-op threads and restore the previous count after
    (commands also run in-process, from tests and scripts)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield count
    finally:
        torch.set_num_threads(before)
