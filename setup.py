"""ament_python package definition: `colcon build` on ROS 2 Jazzy, or the project's own scripts."""

from glob import glob

from setuptools import find_packages, setup

from mosiv_ros.config import STAGE_CONFIGS  # the node list's one home (standard library only)

PACKAGE = "mosiv_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="mosiv_ros developers",
    maintainer_email="mosiv@example.com",
    description="Multi-object system identification from video as a ROS 2 node suite",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [f"{node} = {PACKAGE}.nodes.{node}:main" for node in STAGE_CONFIGS]
        + [f"mosiv = {PACKAGE}.cli:main"],
    },
)
