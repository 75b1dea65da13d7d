"""Where the package's shipped files (config/, firmware/) are, however it was installed."""
from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = "profile_pose_ros"


def ament_prefix() -> Path | None:
    """The install prefix the ament index (AMENT_PREFIX_PATH) has for this package, if any: a colcon
    install (share/, lib/profile_pose_ros/ under it)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    except ImportError:
        return None
    try:
        return Path(get_package_prefix(PACKAGE))
    except (PackageNotFoundError, ValueError, OSError):  # OSError: no AMENT_PREFIX_PATH (pip install)
        return None


def shipped_path(*parts: str) -> Path:
    """A shipped file or folder (config/..., firmware/...): the colcon share dir, then the pip data_files
    prefix, then the source tree; the last candidate when none exists."""
    prefix = ament_prefix()
    candidates = [] if prefix is None else [prefix.joinpath("share", PACKAGE, *parts)]
    candidates.append(Path(sys.prefix).joinpath("share", PACKAGE, *parts))
    candidates.append(Path(__file__).resolve().parent.parent.joinpath(*parts))
    for candidate in candidates:
        if candidate.exists():
            return candidate
    return candidates[-1]


def config_path(name: str) -> Path:
    return shipped_path("config", name)


DEFAULT_GAUGE = "gauge_paper_n5.yaml"
