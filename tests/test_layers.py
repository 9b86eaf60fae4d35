"""The layer rules of DESIGN.md ("Layers"), checked on the source: solver_core never imports
protocol, nodes or zmq; protocol never imports solver_core or nodes; a node never imports another
node (shared code lives in protocol or solver_core, or in the nodes' own base and config)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NODE_SHARED = {"base", "config", "__init__"}  # the node runtime itself, not a node


def _imports(path: Path) -> list[tuple[str, int]]:
    """(absolute-or-relative module name, line) of every import in a file; relative ones as '.name'."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            if node.level and not node.module:  # from . import x
                out += [("." + alias.name, node.lineno) for alias in node.names]
            else:
                out.append((base, node.lineno))
    return out


@pytest.mark.parametrize("layer, forbidden", [
    ("solver_core", ("uuomocap.protocol", "uuomocap.nodes", "zmq")),
    ("protocol", ("uuomocap.solver_core", "uuomocap.nodes")),
])
def test_a_layer_never_imports_what_design_forbids(layer, forbidden):
    bad = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in sorted((ROOT / layer).rglob("*.py"))
           for name, line in _imports(p) if any(name == f or name.startswith(f + ".") for f in forbidden)]
    assert not bad, bad


def test_a_node_never_imports_another_node():
    nodes = {p.stem for p in (ROOT / "nodes").glob("*.py")} - NODE_SHARED
    bad = []
    for p in sorted((ROOT / "nodes").glob("*.py")):
        for name, line in _imports(p):
            target = name.lstrip(".").split(".")[0] if name.startswith(".") else \
                name.split(".")[2] if name.startswith("uuomocap.nodes.") else None
            if target in nodes and target != p.stem:
                bad.append(f"nodes/{p.name}:{line} imports {name}")
    assert not bad, bad
    assert len(nodes) >= 8  # the check saw the node modules
