"""The `ljx` backend through the node, against a stub of Keyence's library built here with the C compiler."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2

from profile_pose_ros.core import render_profile, sample_pose
from profile_pose_ros.core.wire.profiler_protocol import z_counts
from profile_pose_ros.devices.ljx import LjxError, LjxProfileSource
from profile_pose_ros.nodes.messages import points_from_cloud
from profile_pose_ros.nodes.profiler_driver import ProfilerDriverNode

STUB = Path(__file__).parent / "stubs" / "ljxacom_stub.c"
PITCH_COUNTS = 7500  # 75 um in 0.01 um


@pytest.fixture(scope="module")
def stub_library(tmp_path_factory) -> Path:
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler")
    out = tmp_path_factory.mktemp("ljx") / "libljxacom_stub.so"
    subprocess.run([compiler, "-shared", "-fPIC", "-O2", "-pthread", "-o", str(out), str(STUB)], check=True)
    return out


@pytest.fixture
def profiles(gauge, tmp_path, monkeypatch) -> np.ndarray:
    """Three rendered profiles in the library's units, served in turn by the stub."""
    rng = np.random.default_rng(5)
    heights = np.array([z_counts(render_profile(gauge, *sample_pose(gauge, rng), noise_std=5e-6, rng=rng)[:, 1])
                        for _ in range(3)])
    x_start = -1599.5 * PITCH_COUNTS
    path = tmp_path / "profiles.bin"
    header = np.array([3, heights.shape[1], int(x_start), PITCH_COUNTS], dtype=np.int64).astype("<u4")
    path.write_bytes(header.tobytes() + heights.astype("<i4").tobytes())
    monkeypatch.setenv("LJX_STUB_PROFILES", str(path))
    monkeypatch.setenv("LJX_STUB_RATE_HZ", "200")
    return heights


def driver(ros, library: Path) -> ProfilerDriverNode:
    params = {"backend": "ljx", "library_path": str(library), "host": "127.0.0.1", "serial_url": "",
              "diagnostics_period": 0.2}
    return ros.add(ProfilerDriverNode(context=ros.context,
                                      parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))


def test_profiles_stream_from_the_vendor_library(ros, stub_library, profiles, monkeypatch) -> None:
    monkeypatch.setenv("LJX_STUB_INTERRUPT_AFTER", "30")  # one interrupted session: the node reconnects
    node = driver(ros, stub_library)
    received = []
    ros.node("listener").create_subscription(PointCloud2, "profile", received.append, qos_profile_sensor_data)
    assert ros.spin_until(lambda: len(received) >= 60, 20.0), node.link.last_error
    assert node.link.counters.connections >= 2 and "interrupted" in node.link.last_error
    for msg in received[-20:]:
        points = points_from_cloud(msg)
        assert msg.header.frame_id == "profiler"
        z = points[:, 1]
        valid = np.isfinite(z)  # the x grid from the controller's start and pitch
        np.testing.assert_allclose(points[valid, 0], (-1599.5 + np.nonzero(valid)[0]) * 75e-6, atol=1e-7)
        # which of the three profiles it is: the one it equals, invalid points (NaN) included
        matches = [k for k, h in enumerate(profiles)
                   if np.array_equal(np.isnan(z), h < -2 ** 31 + 16)
                   and np.allclose(z[np.isfinite(z)], h[h > -2 ** 31 + 16] * 1e-8, atol=1e-7)]
        assert len(matches) == 1


def test_a_missing_library_is_a_clear_error_not_a_crash(tmp_path) -> None:
    source = LjxProfileSource(str(tmp_path / "nope.so"), "127.0.0.1")
    with pytest.raises(LjxError, match="cannot load the LJ-X library"):
        source.open()


def test_a_wrong_library_is_named(tmp_path) -> None:
    libc = next((p for p in ("/lib/x86_64-linux-gnu/libc.so.6", "/lib/aarch64-linux-gnu/libc.so.6",
                             "/usr/lib/libc.so.6") if Path(p).exists()), None)
    if libc is None:
        pytest.skip("no libc found at the usual paths")
    with pytest.raises(LjxError, match="not the LJ-X8000 library"):
        LjxProfileSource(libc, "127.0.0.1").open()
