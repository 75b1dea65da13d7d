"""What a ROS 2 user installs, run as the user guide says (docs/user_guide.md, section 3): the package
built with colcon into a workspace, `source install/setup.bash`, and every executable started from
install/lib/profile_pose_ros with a Python path on which neither the source tree nor the editable install
comes first. The bringup from the install starts the nodes themselves (never a `ros2 run` wrapper that
would swallow their stop) and leaves nothing behind."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT
from profile_pose_ros.tools.cli import TOOLS as CLI_TOOLS

# argparse tools answer --help; nodes start, show up in the graph, and stop on SIGINT with exit status 0
# (the research and commissioning tools are subcommands of profile_pose)
TOOLS = [["profile_pose_bag"], ["profile_pose_bringup"], ["profile_pose_calibrate"], ["profile_pose"]] + [["profile_pose", name] for name in CLI_TOOLS]
NODES = {"pose_estimator": ["pose_estimator"], "profiler_driver": ["profiler_driver"],
         "pd_compensator": ["pd_compensator"], "motoplus_bridge": ["motoplus_bridge"], "sim_cell": ["sim_cell"],
         "cell_container": ["profiler_driver", "pose_estimator", "pd_compensator", "motoplus_bridge"],
         "profiler_estimator": ["profiler_driver", "pose_estimator"],
         "compensator_bridge": ["pd_compensator", "motoplus_bridge"],
         "bag_recorder": ["bag_recorder"], "bag_player": ["bag_player"]}

# the guide's commands, in the test's venv and workspace
GUIDE = """set -e
source "{venv}/bin/activate"
"{ws}/src/profile_pose_ros/scripts/build_tf2_msgs.sh"
export AMENT_PREFIX_PATH=$VIRTUAL_ENV
cd "{ws}" && colcon build --packages-select profile_pose_ros --event-handlers console_direct- >/dev/null
source install/setup.bash
env -0
"""


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> tuple[Path, dict]:
    """(the install prefix, the environment `source install/setup.bash` gives)."""
    ws = tmp_path_factory.mktemp("ws")
    shutil.copytree(ROOT, ws / "src" / "profile_pose_ros", ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "runs", "*.egg-info", "__pycache__"))
    venv = Path(sys.executable).parent.parent
    result = subprocess.run(["bash", "-c", GUIDE.format(venv=venv, ws=ws)], capture_output=True, timeout=600,
                            env={k: v for k, v in os.environ.items() if k not in ("AMENT_PREFIX_PATH", "PYTHONPATH")})
    assert result.returncode == 0, result.stderr.decode(errors="replace")
    env = dict(item.split("=", 1) for item in result.stdout.decode().split("\0") if "=" in item)
    prefix = ws / "install" / "profile_pose_ros"
    site = next((prefix / "lib").glob("python3*/site-packages"))
    assert env["PYTHONPATH"].split(":")[0] == str(site)  # the installed copy comes first
    assert str(prefix) in env["AMENT_PREFIX_PATH"].split(":")
    return prefix, env


def test_the_installed_package_is_the_one_that_runs(workspace) -> None:
    prefix, env = workspace
    probe = subprocess.run([sys.executable, "-c", "import profile_pose_ros, profile_pose_ros.sim.motoplus_app as m; "
                            "print(profile_pose_ros.__file__); print(m.firmware_dir())"],
                           capture_output=True, text=True, env=env, cwd="/", timeout=60)
    module, firmware = probe.stdout.split()
    assert Path(module).is_relative_to(prefix) and Path(firmware).is_relative_to(prefix), probe.stderr


@pytest.mark.parametrize("tool", TOOLS, ids=" ".join)
def test_every_installed_tool_answers_help(workspace, tool) -> None:
    prefix, env = workspace
    executable, *subcommand = tool
    run = subprocess.run([str(prefix / "lib" / "profile_pose_ros" / executable), *subcommand, "--help"],
                         capture_output=True, text=True, env=env, cwd="/", timeout=120)
    assert run.returncode == 0 and "usage" in run.stdout.lower(), run.stdout + run.stderr
    if subcommand:  # argparse names the tool as it is typed
        assert f"profile_pose {subcommand[0]}" in run.stdout


@pytest.mark.parametrize("executable", sorted(NODES))
def test_every_installed_node_starts_and_stops_cleanly(ros, workspace, tmp_path, executable) -> None:
    prefix, env = workspace
    args = {"sim_cell": ["-p", "profiler_port:=0", "-p", "mcu_port:=0", "-p", "robot_port:=0"],
            "bag_recorder": ["-p", f"output:={tmp_path / 'recorded'}"],
            "bag_player": ["-p", f"bag:={tmp_path / 'played'}", "-p", "exit_when_done:=false"]}.get(executable, [])
    if executable == "bag_player":
        _one_message_bag(tmp_path / "played")
    process = subprocess.Popen([str(prefix / "lib" / "profile_pose_ros" / executable), "--ros-args", *args],
                               env=dict(env, ROS_DOMAIN_ID=str(ros.domain_id)), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        watcher = ros.node("installed_watch")
        names = lambda: set(watcher.get_node_names())  # noqa: E731
        assert ros.spin_until(lambda: set(NODES[executable]) <= names() or process.poll() is not None, 120.0)
        assert process.poll() is None, process.communicate()[0]
        process.send_signal(signal.SIGINT)
        output = process.communicate(timeout=30)[0]
        assert process.returncode == 0, output
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def _one_message_bag(path: Path) -> Path:
    from profile_pose_ros.bags.reader import typestore
    from profile_pose_ros.bags.writer import BagWriter
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__String as String

    writer = BagWriter(path)
    writer.add_topic("/a", "std_msgs/msg/String")
    writer.write("/a", 10 ** 9, bytes(typestore().serialize_cdr(String(data="a"), "std_msgs/msg/String")))
    writer.close()
    return path


def domain_processes(domain_id: int) -> list[int]:
    """Processes started with this ROS_DOMAIN_ID (the witness: whatever the bringup's own records say)."""
    found = []
    marker = f"ROS_DOMAIN_ID={domain_id}".encode()
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                if marker in (proc / "environ").read_bytes().split(b"\0"):
                    found.append(int(proc.name))
            except OSError:
                pass
    return found


MAX_PROFILE_AGE_NS = 1_000_000_000


def replayed_live_with_clock(ros, prefix: Path, env: dict, bag: Path) -> None:
    """As `ros2 bag play --clock` into a fresh estimator with use_sim_time: the installed bag_player plays
    the recorded profiles and the bag's time on /clock, and every pose the installed estimator publishes
    is, byte for byte, the one recorded for that profile. The estimator runs with cell.yaml and a max_profile_age
    of 1 s: by the wall clock every profile is older than that (the bag ended seconds ago), so only the bag's
    time on /clock makes them fresh. Not cell.yaml's 50 ms: the player sends each profile at its log time, when
    the recorder received it, and a loaded runner's recorder lags the live estimator by tens of ms."""
    from rosbags.highlevel import AnyReader
    from rosgraph_msgs.msg import Clock
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from profile_pose_ros.nodes.messages import cdr_stamp_ns

    with AnyReader([bag]) as reader:
        recorded = {cdr_stamp_ns(data): data for connection, _, data in reader.messages(
            [c for c in reader.connections if c.topic == "/pose_with_covariance"])}
        start, end = reader.start_time, reader.end_time
    from diagnostic_msgs.msg import DiagnosticArray

    live, clock, reports = {}, [], {}
    listener = ros.node("replay_listener")
    listener.create_subscription(PoseWithCovarianceStamped, "/pose_with_covariance",
                                 lambda data: live.setdefault(cdr_stamp_ns(data), data), 100, raw=True)
    listener.create_subscription(Clock, "/clock", clock.append, 10)
    # the replay estimator's and player's own counts, for a failure to say where the poses went
    listener.create_subscription(DiagnosticArray, "/diagnostics", lambda array: reports.update(
        {status.name: {v.key: v.value for v in status.values} for status in array.status}), 50)
    lib = prefix / "lib" / "profile_pose_ros"
    run_env = dict(env, ROS_DOMAIN_ID=str(ros.domain_id))
    cell_yaml = prefix / "share" / "profile_pose_ros" / "config" / "cell.yaml"  # what the bringup ran with
    estimator = subprocess.Popen([str(lib / "pose_estimator"), "--ros-args", "--params-file", str(cell_yaml),
                                  "-p", "use_sim_time:=true", "-p", f"max_profile_age:={MAX_PROFILE_AGE_NS * 1e-9}"],
                                 env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # the player waits for a subscriber only so long (wait_timeout): start it once the estimator listens, to
    # the profiles and to /clock (before its first /clock message its time is zero, and every profile stale)
    assert ros.spin_until(lambda: listener.count_subscribers("/profile") > 0
                          and listener.count_subscribers("/clock") > 1, timeout=120.0), "no estimator"
    # a quick runner gets here within a second of the bag's end: let its profiles go stale by the wall clock
    assert ros.spin_until(lambda: time.time_ns() - end > 2 * MAX_PROFILE_AGE_NS, timeout=3 * MAX_PROFILE_AGE_NS * 1e-9)
    player = subprocess.Popen([str(lib / "bag_player"), "--ros-args", "-p", f"bag:={bag}", "-p", "clock:=100.0",
                               "-p", "topics:=['/profile']", "-p", "wait_for_subscribers:=true",
                               # the listener here is the second /clock subscriber: give the player time to
                               # discover it, and the bag's half second of time enough wall time to reach it
                               "-p", "discovery_grace:=2.0", "-p", "rate:=0.25", "-p", "exit_when_done:=false"],
                              env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        # the player's profiles ride a sensor-data queue: a loaded runner may lose a few
        assert ros.spin_until(lambda: clock and len(live.keys() & recorded.keys()) >= 0.9 * len(recorded),
                              timeout=120.0), (len(live), len(recorded), len(live.keys() & recorded.keys()),
                                               reports, _bringup_estimator_log(bag))
    finally:
        for process in (player, estimator):
            process.send_signal(signal.SIGINT)
            process.wait(timeout=30)
    assert all(start <= c.clock.sec * 10**9 + c.clock.nanosec <= end for c in clock)  # the bag's time
    common = live.keys() & recorded.keys()
    assert {stamp: live[stamp] for stamp in common} == {stamp: recorded[stamp] for stamp in common}


def _bringup_estimator_log(bag: Path) -> str:
    """The last lines the recording bringup's estimator logged (beside its bag): what it refused or skipped."""
    log = bag.parent / "pose_estimator.log"
    return "\n".join(log.read_text(errors="replace").splitlines()[-15:]) if log.exists() else "no log"


def parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


# once more on failure: a clean-clone CI run on a loaded runner matched 78 of the 89 recorded poses in the
# live replay (0.9 needed), the rest lost on the profile's sensor-data queue or taken before /clock reached
# the estimator; everything else this test checks had passed
@pytest.mark.flaky(reruns=1)
@pytest.mark.alone  # the live replay counts the poses the estimator keeps up with
@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL"])
def test_the_bringup_from_the_install_owns_its_nodes(ros, workspace, tmp_path, how) -> None:
    from profile_pose_ros.tools.processes import fresh_domain_id

    prefix, env = workspace
    domain = fresh_domain_id()
    record = ["--record"] if how == "SIGTERM" else []
    bringup = subprocess.Popen([str(prefix / "lib" / "profile_pose_ros" / "profile_pose_bringup"), "--domain-id",
                                str(domain), "--out", str(tmp_path), *record], env=dict(env, ROS_DOMAIN_ID=str(domain)),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in bringup.stdout:  # the bringup says when it is ready: profiles, poses, corrections flow
            lines.append(line)
            if line.startswith("ready in") or "profile_pose_bringup:" in line:
                break
        assert any(line.startswith("ready in") for line in lines), "".join(lines)
        nodes = [pid for pid in domain_processes(domain) if pid != bringup.pid]
        assert len(nodes) == 5 + len(record) and all(parent(pid) == bringup.pid for pid in nodes)  # no wrapper
        scripts = [Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[1].decode() for pid in nodes]
        assert all(Path(script).is_relative_to(prefix) for script in scripts), scripts  # python <installed exe>
        bringup.send_signal(getattr(signal, how))
        bringup.wait(timeout=60)
        end = time.monotonic() + 30.0  # SIGKILL: the nodes get SIGTERM from the kernel, and take their clean path
        while (survivors := domain_processes(domain)) and time.monotonic() < end:
            time.sleep(0.1)  # polling /proc for the condition, with a deadline
        assert survivors == [], [Path(f"/proc/{pid}/cmdline").read_bytes()[:200] for pid in survivors]
        if how == "SIGTERM":
            output = bringup.stdout.read()
            assert bringup.returncode == 0 and "stopped" in output, output
            # the recording re-estimated offline by the installed replay, with the installed cell.yaml: the
            # estimator's poses bit for bit
            bag = next(tmp_path.glob("*-bringup/bag"))
            from profile_pose_ros.bags.writer import _mcap_compression
            assert {_mcap_compression(path) for path in bag.glob("*.mcap")} == {"zstd"}  # cell.yaml's too
            assert "ros_distro: jazzy" in (bag / "metadata.yaml").read_text()  # as rosbag2 writes it
            script = ("import json, sys; from profile_pose_ros.tools.replay import estimator_values, replay; "
                      "print(json.dumps(replay(sys.argv[1], estimator_values(sys.argv[2], {}))))")
            cell_yaml = prefix / "share" / "profile_pose_ros" / "config" / "cell.yaml"
            run = subprocess.run([sys.executable, "-c", script, str(bag), str(cell_yaml)], capture_output=True,
                                 text=True, env=env, cwd="/", timeout=300)
            assert run.returncode == 0, run.stderr
            report = json.loads(run.stdout.splitlines()[-1])
            # every pose recorded with its profile is reproduced bit for bit (a short run: ~80 profiles)
            assert report["compared"] > 0 and report["identical"] == report["compared"], report
            replayed_live_with_clock(ros, prefix, env, bag)
    finally:
        if bringup.poll() is None:
            bringup.kill()
            bringup.wait()
