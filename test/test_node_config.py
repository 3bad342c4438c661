"""config/odometry.yaml and config/trainer.yaml set exactly the parameters the nodes declare, with the
declared types (a ROS parameter file with 1 where the node declares 1.0 fails at start on Jazzy).

The nodes import rclpy, so their PARAMETERS tables are read from the source, not imported.
"""

from __future__ import annotations

import ast
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


class _ModuleNames(dict):
    """Names the PARAMETERS table uses: literal module constants as they are, anything else a string."""

    def __init__(self, tree: ast.Module) -> None:
        super().__init__()
        for node in tree.body:
            if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
                try:
                    self[node.targets[0].id] = ast.literal_eval(node.value)
                except ValueError:
                    self[node.targets[0].id] = "a string"  # e.g. DEFAULT_STORE = os.path.join(...)


def declared(node_file: str) -> dict:
    tree = ast.parse((ROOT / "nocal_ros" / "ros" / node_file).read_text())
    for node in tree.body:
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "PARAMETERS":
            return eval(compile(ast.Expression(node.value), node_file, "eval"), {}, _ModuleNames(tree))  # noqa: S307
    raise AssertionError(f"no PARAMETERS table in {node_file}")


def check(config: str, node_file: str, name: str, defaults) -> None:
    parameters = yaml.safe_load((ROOT / "config" / config).read_text())[name]["ros__parameters"]
    declared_names = set(defaults)
    assert set(parameters) - declared_names - {"bags", "use_sim_time"} == set(), "set but never declared"
    for key, value in parameters.items():
        if key in defaults:
            expected = type(defaults[key])
            actual = type(value[0]) if isinstance(value, list) and isinstance(defaults[key], list) else type(value)
            if isinstance(defaults[key], list):
                expected = type(defaults[key][0])
            assert actual is expected, f"{config}: {key} is {actual.__name__}, the node declares {expected.__name__}"
    return set(parameters)


def test_odometry_config_matches_the_node():
    defaults = declared("odometry_node.py")
    assert check("odometry.yaml", "odometry_node.py", "odometry_node", defaults) == set(defaults)  # documents all


def test_trainer_config_matches_the_node():
    defaults = {k: v[0] for k, v in declared("trainer_node.py").items()}
    assert check("trainer.yaml", "trainer_node.py", "trainer_node", defaults) == set(defaults)


def test_the_rviz_config_shows_what_the_odometry_node_publishes():
    """config/odometry.rviz subscribes to the node's topics (its publishers' names, at the root namespace
    the launch file uses) and fixes the view in the configured map frame, so it does not drift from them."""
    source = (ROOT / "nocal_ros" / "ros" / "odometry_node.py").read_text()
    published = {"/" + node.args[1].value for node in ast.walk(ast.parse(source))
                 if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "create_publisher"
                 and isinstance(node.args[1], ast.Constant)}
    manager = yaml.safe_load((ROOT / "config" / "odometry.rviz").read_text())["Visualization Manager"]
    topics = {display["Topic"]["Value"] for display in manager["Displays"] if "Topic" in display}
    assert topics == {"/odom", "/keyframe_path", "/map_points"} and topics <= published
    parameters = yaml.safe_load((ROOT / "config" / "odometry.yaml").read_text())["odometry_node"]["ros__parameters"]
    assert manager["Global Options"]["Fixed Frame"] == parameters["map_frame"] == declared("odometry_node.py")["map_frame"]
    setup = (ROOT / "setup.py").read_text()
    assert 'glob("config/*.rviz")' in setup  # installed beside the parameter files
