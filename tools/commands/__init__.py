"""CLI verbs, one module per verb group, discovered by ``uuomocap.cli``.

Shared helpers for verbs live here so every verb behaves the same:
``UserError`` for one-line errors, ``emit`` for text-or-JSON output.
"""

from __future__ import annotations

import json
import sys
from typing import Any

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


def emit(args: Any, data: dict, text: str | None = None) -> None:
    """Print ``data`` as JSON when ``--json`` was given, else ``text`` (or key: value lines)."""
    if getattr(args, "json", False):
        json.dump(_jsonable(data), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return
    if text is None:
        text = "\n".join(f"{k}: {v}" for k, v in data.items())
    print(text)


def add_json_flag(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON instead of text")
