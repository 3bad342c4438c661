"""package.xml declares exactly the ROS packages the code imports (rosdep installs from it on robots).

Real Jazzy showed ``<exec_depend>tf2_ros</exec_depend>``: the C++ package, which pulls in rclcpp,
while the ``tf2_ros`` Python module comes from ``tf2_ros_py``.
"""

from __future__ import annotations

import ast
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Python module -> the ROS package that provides it, where the names differ.
PROVIDED_BY = {"tf2_ros": "tf2_ros_py"}
ROS_MODULES = {"rclpy", "tf2_ros", "launch", "launch_ros", "ament_index_python"}


def is_ros_module(name: str) -> bool:
    return name in ROS_MODULES or name.endswith(("_msgs", "_srvs", "_interfaces"))


def imported_ros_packages(paths) -> set[str]:
    packages = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if is_ros_module(top):
                    packages.add(PROVIDED_BY.get(top, top))
    return packages


def declared(kind: str) -> set[str]:
    return {element.text.strip() for element in ET.parse(ROOT / "package.xml").getroot().iter(kind)}


def test_every_ros_import_is_declared_and_every_declared_ros_package_is_used():
    runtime = imported_ros_packages([*(ROOT / "nocal_ros").rglob("*.py"), *(ROOT / "launch").glob("*.py")])
    tests = imported_ros_packages((ROOT / "test").glob("*.py"))
    exec_depends = {name for name in declared("exec_depend") if not name.startswith("python3-")}
    test_depends = {name for name in declared("test_depend") if not name.startswith("python3-")}
    assert "tf2_ros" not in exec_depends and "tf2_ros_py" in runtime
    assert runtime - exec_depends == set(), "imported by the package but not an exec_depend"
    assert tests - exec_depends - test_depends == set(), "imported by the tests but not declared"
    assert exec_depends - runtime == set(), "declared but never imported"
    assert test_depends - tests == set(), "test_depend never imported by a test"
