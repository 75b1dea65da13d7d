"""The package is a correct ament_python package: catkin_pkg accepts package.xml (otherwise colcon
silently builds it as plain Python and `ros2 run` cannot find it), and a colcon build installs the
executables under lib/profile_pose_ros with the ament_prefix_path hook."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

from catkin_pkg.package import parse_package

from conftest import ROOT

EXECUTABLES = ["pose_estimator"]


def test_package_xml_is_valid_format_3():
    package = parse_package(str(ROOT / "package.xml"))
    package.validate()
    assert package.package_format == 3
    assert package.get_build_type() == "ament_python"
    depends = {d.name for d in package.exec_depends}
    assert {"rclpy", "sensor_msgs", "geometry_msgs", "std_msgs", "diagnostic_msgs", "std_srvs"} <= depends
    assert (ROOT / "resource" / "profile_pose_ros").is_file()
    # every third-party module the package imports is an exec_depend, or named in the pip comment
    keys = {"numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml", "serial": "python3-serial",
            "matplotlib": "python3-matplotlib", "tqdm": "python3-tqdm"}
    comment = (ROOT / "package.xml").read_text().split("No rosdep keys")[1].split("-->")[0]
    pip_names = {"control": "python-control", "cv2": "opencv-python-headless"}
    for module in sorted(imported_modules()):
        assert keys.get(module, module) in depends or pip_names.get(module, module) in comment, module


def imported_modules() -> set[str]:
    import ast

    roots = set()
    for path in (ROOT / "profile_pose_ros").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                roots |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                roots.add(node.module.split(".")[0])
    return {r for r in roots if r not in sys.stdlib_module_names and r != "profile_pose_ros"}


def test_colcon_build_installs_ros2_run_layout(tmp_path):
    workspace = tmp_path / "ws"
    (workspace / "src").mkdir(parents=True)
    source = workspace / "src" / "profile_pose_ros"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".venv", ".git", "build", "install", "log",
                                                                 "runs", "*.egg-info", "__pycache__"))
    colcon = Path(sys.executable).parent / "colcon"
    result = subprocess.run([str(colcon), "build", "--event-handlers", "console_direct-"], cwd=workspace,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    prefix = workspace / "install" / "profile_pose_ros"
    for exe in EXECUTABLES:
        assert os.access(prefix / "lib" / "profile_pose_ros" / exe, os.X_OK), exe
    share = prefix / "share" / "profile_pose_ros"
    assert (share / "hook" / "ament_prefix_path.dsv").is_file()
    assert (share / "package.xml").is_file() and (share / "config" / "gauge_paper_n5.yaml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "profile_pose_ros").is_file()
    # What `ros2 run profile_pose_ros pose_estimator` would do after sourcing the workspace: the installed
    # executable starts, and finds the shipped gauge through the ament index (here: refuses a bad one).
    site = next((prefix / "lib").glob("python3*/site-packages"))
    # every source module is installed (a folder without __init__.py was skipped by find_packages, and an
    # editable venv hid that: sim_cell could not start from a colcon install)
    for module in sorted((ROOT / "profile_pose_ros").rglob("*.py")):
        assert (site / module.relative_to(ROOT)).is_file(), f"{module.relative_to(ROOT)} is not installed"
    env = dict(os.environ, AMENT_PREFIX_PATH=str(prefix), PYTHONPATH=str(site))
    run = subprocess.run([str(prefix / "lib" / "profile_pose_ros" / "pose_estimator"), "--ros-args", "-p",
                          "gauge_file:=/nonexistent/gauge.yaml"], capture_output=True, text=True, timeout=60,
                         env=env)
    assert run.returncode == 1 and "/nonexistent/gauge.yaml: not found" in run.stderr
    probe = subprocess.run([sys.executable, "-c", "import profile_pose_ros.resources as r; "
                            "print(r.__file__); print(r.config_path('gauge_paper_n5.yaml'))"],
                           capture_output=True, text=True, timeout=60, env=env, cwd=workspace)
    module_file, config = probe.stdout.split()
    assert Path(module_file).is_relative_to(site)  # the installed copy, not the source tree
    assert Path(config).is_relative_to(share)  # found through the ament index
    # sim_cell's robot controller is the C application, built from the installed sources
    controller = subprocess.run([sys.executable, "-c", "from profile_pose_ros.sim import motoplus_app as m, "
                                 "robot_controller as r; a = m.HostApplication(r.configuration(r.DEFAULT_LIMITS, 3), port=0); "
                                 "print(m.firmware_dir()); print(a.start()); a.stop()"],
                                capture_output=True, text=True, timeout=300, env=env, cwd=workspace)
    assert controller.returncode == 0, controller.stderr
    firmware, port = controller.stdout.split()
    assert Path(firmware).is_relative_to(share) and int(port) > 0
