"""ament_python package: `colcon build` + `ros2 run profile_pose_ros <exe>`, or a plain pip install."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "profile_pose_ros"

# Executable name -> module; the node name is the executable name (DESIGN.md), except the containers'
# (cell_container, profiler_estimator, compensator_bridge), which hold several nodes under their own names.
EXECUTABLES = {
    "pose_estimator": "profile_pose_ros.nodes.pose_estimator:main",
    "profiler_driver": "profile_pose_ros.nodes.profiler_driver:main",
    "sim_cell": "profile_pose_ros.nodes.sim_cell:main",
    "pd_compensator": "profile_pose_ros.nodes.pd_compensator:main",
    "motoplus_bridge": "profile_pose_ros.nodes.motoplus_bridge:main",
    "cell_container": "profile_pose_ros.nodes.cell_container:main",  # the four loop nodes in one process
    "profiler_estimator": "profile_pose_ros.nodes.profiler_estimator:main",  # driver and estimator in one process
    "compensator_bridge": "profile_pose_ros.nodes.compensator_bridge:main",  # compensator and bridge in one process
    "bag_recorder": "profile_pose_ros.nodes.bag_recorder:main",
    "bag_player": "profile_pose_ros.nodes.bag_player:main",
    "profile_pose_bag": "profile_pose_ros.tools.bag_cli:main",
    "profile_pose_bringup": "profile_pose_ros.tools.bringup:main",
    "profile_pose_calibrate": "profile_pose_ros.nodes.calibrate:main",  # commissioning: where gauge and profiler sit
    "profile_pose": "profile_pose_ros.tools.cli:main",  # the research, benchmark and commissioning tools
}

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*.yaml"))),
        # the MotoPlus application's sources: sim_cell builds its controller from them
        (f"share/{PACKAGE}/firmware/motoplus", sorted(glob("firmware/motoplus/*.[ch]") + glob("firmware/motoplus/*.md")
                                                     + ["firmware/motoplus/Makefile", "firmware/motoplus/vectors.txt"])),
        (f"share/{PACKAGE}/firmware/motoplus/host", sorted(glob("firmware/motoplus/host/*.[ch]"))),
    ],
    install_requires=["setuptools", "numpy", "scipy", "PyYAML", "numba", "pyserial", "rosbags"],
    extras_require={"benchmark": ["opencv-python-headless"]},
    zip_safe=False,
    maintainer="profile_pose_ros maintainers",
    maintainer_email="maintainers@profile-pose-ros.org",
    description="6-DoF pose from a 2D laser profile of a faceted gauge, and closed-loop robot correction.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={"console_scripts": [f"{name} = {target}" for name, target in EXECUTABLES.items()]},
)
