"""Reading ROS 2 parameter files (`node: ros__parameters: ...`, `/**` wildcards) the way a node started
with `--params-file` would see them, for tools that run a node's computation offline."""
from __future__ import annotations

from pathlib import Path

import yaml


def node_parameters(path: str | Path, node_name: str, namespace: str = "", declared: set[str] | None = None) -> dict:
    """The parameters `node_name` in `namespace` gets from the file: the `/**` block (only the `declared`
    names, when given: the block is shared, and a node ignores what it does not declare), then its own."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a ROS 2 parameter file (no node blocks)")
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
    names = ["/**", f"/**/{node_name}", node_name, f"/{node_name}", f"{namespace}/{node_name}",
             f"{namespace.lstrip('/')}/{node_name}"]
    values: dict = {}
    for key in dict.fromkeys(names):  # in order, without repeats
        block = data.get(key)
        if isinstance(block, dict):
            block_values = block.get("ros__parameters") or {}
            if key == "/**" and declared is not None:
                block_values = {k: v for k, v in block_values.items() if k in declared}
            values.update(block_values)
    return values


def parse_overrides(items: list[str]) -> dict:
    """`name:=value` pairs as on a ROS command line, values read as YAML."""
    values = {}
    for item in items:
        name, sep, text = item.partition(":=")
        if not sep or not name:
            raise ValueError(f"expected name:=value, got {item!r}")
        values[name] = yaml.safe_load(text)
    return values
