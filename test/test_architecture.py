"""The package's import graph, read from its source: no cycle (imports inside functions count), core/ never
reaches ROS, and core's rooms import only the rooms below them."""
from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

import profile_pose_ros

PACKAGE = Path(profile_pose_ros.__file__).resolve().parent
# core/'s rooms, bottom-up, as core/__init__ lists them: a room may import itself and those before it
CORE_ROOMS = ("model", "timing", "compiled", "wire", "estimation", "control", "design", "commissioning")
# the package's folders, bottom-up
LAYERS = ("core", "devices", "bags", "sim", "nodes", "tools")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The package's modules this one imports, anywhere in it (functions too); `from pkg import mod` names mod."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]  # a name inside a module: the module
            if target and target != name:
                found.add(target)
    return found


def external_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    found = modules()
    known = set(found)
    # a package's __init__ that re-exports its children is their face, not a dependency of theirs
    return {name: imports_of(name, path, known) for name, path in found.items()}


def room(module: str, depth: int) -> str:
    parts = module.split(".")
    return parts[depth] if len(parts) > depth else ""


def test_the_reader_sees_known_imports(graph) -> None:
    """The graph is read right: an import at module level, one inside a function, and a relative one."""
    assert "profile_pose_ros.core.model.gauge" in graph["profile_pose_ros.core.estimation.residuals"]
    assert "profile_pose_ros.core.compiled.estimate_kernel" in graph["profile_pose_ros.core.compiled.loader"]
    assert "profile_pose_ros.core.compiled.loader" in graph["profile_pose_ros.core.wire.profile_cloud"]


def test_no_import_cycle(graph) -> None:
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


def test_folders_import_only_the_layers_below_them(graph) -> None:
    upward = [(a, b) for a, targets in graph.items() for b in targets
              if room(a, 1) in LAYERS and room(b, 1) in LAYERS
              and LAYERS.index(room(b, 1)) > LAYERS.index(room(a, 1))]
    assert not upward, upward


def test_core_rooms_read_bottom_up(graph) -> None:
    core = {a: t for a, t in graph.items() if room(a, 1) == "core" and room(a, 2) in CORE_ROOMS}
    assert {room(a, 2) for a in core} == set(CORE_ROOMS)  # every room exists; none unlisted holds modules
    upward = [(a, b) for a, targets in core.items() for b in targets
              if room(b, 1) == "core" and (room(b, 2) not in CORE_ROOMS
                                             or CORE_ROOMS.index(room(b, 2)) > CORE_ROOMS.index(room(a, 2)))]
    assert not upward, upward
    loose = [m for m in graph if room(m, 1) == "core" and m.count(".") == 2 and room(m, 2) not in CORE_ROOMS]
    assert not loose, loose  # a module beside the rooms


def test_core_never_reaches_ros_and_only_compiled_imports_numba() -> None:
    for name, path in modules().items():
        if room(name, 1) != "core":
            continue
        outside = external_imports(path)
        assert not outside & {"rclpy", "rosidl_runtime_py", "sensor_msgs", "geometry_msgs"}, name
        if room(name, 2) != "compiled":
            assert "numba" not in outside, name
