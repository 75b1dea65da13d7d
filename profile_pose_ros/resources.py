"""Where the package's shipped files (config/) are, however it was installed."""
from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = "profile_pose_ros"


def config_path(name: str) -> Path:
    """A file from config/: colcon share dir, then the pip data_files prefix, then the source tree."""
    candidates = []
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            candidates.append(Path(get_package_share_directory(PACKAGE)) / "config" / name)
        except (PackageNotFoundError, ValueError, OSError):  # OSError: no AMENT_PREFIX_PATH (pip install)
            pass
    except ImportError:
        pass
    candidates.append(Path(sys.prefix) / "share" / PACKAGE / "config" / name)
    candidates.append(Path(__file__).resolve().parent.parent / "config" / name)
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return candidates[-1]


DEFAULT_GAUGE = "gauge_paper_n5.yaml"
