"""Local mapping: its worker process (solves run there, and a process that dies is replaced), and a keyframe
that tracking posed before a solve landed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest
from test_bundle_adjustment import make_window
from test_camera_initialisation import noisy_window, problem_through, tracked_through_the_guess

from nocal_ros.geometry import so3_exp
from nocal_ros.odometry.calibration import OnlineCamera
from nocal_ros.odometry import local_mapping
from nocal_ros.odometry.camera_initialisation import initialise_camera
from nocal_ros.odometry.local_mapping import SOLVER_RESTARTS, LocalMapping, solver_processes
from nocal_ros.odometry.map import LocalMap


def test_a_solver_process_that_died_is_replaced_and_the_solve_still_runs():
    """The solver process killed (as the out-of-memory killer would) between two solves: the next solve
    starts a new process, gives the same answer as before, and says so in ``solver_restarts``; a
    process killed after the last restart allowed fails the solve."""
    camera, poses, points, keyframe_index, point_index, pixels = noisy_window(3)
    problem = problem_through(camera, poses, points, keyframe_index, point_index, pixels)
    mapping = LocalMapping(OnlineCamera(camera, "file"), synchronous=False)
    try:
        first = mapping._solve(problem)
        (pid,) = list(mapping._solvers[0]._processes)
        os.kill(pid, signal.SIGKILL)
        again = mapping._solve(problem)
        assert first.success and again.success
        np.testing.assert_allclose(again.poses, first.poses, atol=1e-12)
        assert mapping.solver_restarts == 1
        assert pid not in mapping._solvers[0]._processes
        # One that keeps dying is not replaced for ever: past SOLVER_RESTARTS the solve fails.
        mapping.solver_restarts = SOLVER_RESTARTS
        (pid,) = list(mapping._solvers[0]._processes)
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(BrokenProcessPool):
            mapping._solve(problem)
    finally:
        mapping.close()


def test_a_camera_initialisation_spread_over_two_solver_processes_chooses_as_one_process_does(monkeypatch):
    """A live stream's first camera initialisation, its twelve candidates spread over two solver
    processes, one of them killed before it starts: the process is replaced, and the choice and every
    candidate's figures are those of the same initialisation in this process, to the bit."""
    camera, _, problem = tracked_through_the_guess(2)
    expected, expected_report = initialise_camera(problem)
    monkeypatch.setattr(local_mapping, "solver_processes", lambda: 2)
    mapping = LocalMapping(OnlineCamera(problem.calibration, "guess"), synchronous=False)
    try:
        assert len(mapping._solvers) == 2
        mapping._solvers[1].submit(int).result()  # started, so that there is a process to kill
        (pid,) = list(mapping._solvers[1]._processes)
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        while not mapping._solvers[1]._broken and time.monotonic() < deadline:  # the pool has seen it die
            time.sleep(0.01)
        used = []
        spread = mapping._map_in_processes
        monkeypatch.setattr(mapping, "_map_in_processes", lambda f, items: used.append(len(items)) or spread(f, items))
        solution = mapping._solve(problem, hypotheses=True)
        assert used == [len(expected_report)]  # the candidates went through the spread
        assert mapping.solver_restarts == 1
        np.testing.assert_array_equal(np.array(mapping.initialisation_report), np.array(expected_report))
        np.testing.assert_array_equal(solution.poses, expected.poses)
        assert solution.calibration.fx == expected.calibration.fx
        assert abs(solution.calibration.fx / camera.fx - 1) < 0.02
    finally:
        mapping.close()


def test_solver_processes_leave_a_core_for_tracking(monkeypatch):
    for cores, processes in [(1, 1), (2, 1), (3, 2), (8, 4), (64, 4)]:
        monkeypatch.setattr(os, "sched_getaffinity", lambda _pid, n=cores: set(range(n)))
        assert solver_processes() == processes


def test_the_solver_process_loads_its_modules_before_the_first_solve_and_never_torch():
    """The solver process's start imports the solver and the camera initialisation, and neither loads
    torch: loaded at the first camera initialisation of a live stream, torch took 1.5 s of it."""
    code = ("import json, sys\n"
            "from nocal_ros.odometry.local_mapping import _import_solver\n"
            "_import_solver()\n"
            "print(json.dumps(sorted(m for m in ('torch', 'cv2', 'scipy.sparse', 'nocal_ros.odometry.camera_initialisation') if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120).stdout
    assert json.loads(out) == ["cv2", "nocal_ros.odometry.camera_initialisation", "scipy.sparse"]


def test_a_keyframe_posed_before_a_solve_landed_is_posed_again_on_the_map_as_it_is_now():
    """OpenCV-projected landmarks without noise: the newest keyframe, posed by tracking in the map's
    previous version (3 deg and 5 cm off the map as it is now), is posed again by PnP to the pose its
    pixels were projected from before it is triangulated from, and the map's version counts the change;
    a keyframe posed in the map's present version, and one posed again already, are left as they are."""
    camera, poses, _, points, keyframe_index, point_index, pixels = make_window("plumb_bob", 4, keyframes=6, landmarks=120)
    stale = poses[5].copy()
    stale[:3, :3] = so3_exp(np.radians(3.0) * np.array([0.6, 0.8, 0.0])) @ stale[:3, :3]
    stale[:3, 3] += [0.03, -0.04, 0.0]
    local_map = LocalMap()
    for k in range(6):
        rows = keyframe_index == k
        local_map.add_keyframe(k, k, stale if k == 5 else poses[k], point_index[rows], pixels[rows])
    local_map.landmarks = {j: point for j, point in enumerate(points)}
    mapping = LocalMapping(OnlineCamera(camera, "file"), synchronous=True)
    newest, previous = local_map.keyframes[5], local_map.keyframes[4]
    assert not mapping.pose_again(local_map, newest)  # posed in the map's present version
    np.testing.assert_array_equal(newest.T_w_c, stale)
    local_map.version += 1  # a solve landed after tracking posed it
    assert mapping.pose_again(local_map, newest)
    np.testing.assert_allclose(newest.T_w_c, poses[5], atol=1e-6)
    assert local_map.version == 2  # a change of the map, which tracking must see
    assert newest.map_version == local_map.version and not mapping.pose_again(local_map, newest)
    before = previous.T_w_c.copy()
    previous.map_version = local_map.version
    assert not mapping.pose_again(local_map, previous)
    np.testing.assert_array_equal(previous.T_w_c, before)


SOLVER_MODULES_SCRIPT = """\
import json, sys
{top_level_import}


def heavy_modules():
    return sorted(m for m in ("torch", "rclpy") if m in sys.modules)


if __name__ == "__main__":
    import numpy as np
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry.calibration import OnlineCamera
    from nocal_ros.odometry.local_mapping import LocalMapping

    calibration = CameraCalibration(64, 48, np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]]))
    mapping = LocalMapping(OnlineCamera(calibration, "file"), synchronous=False)
    try:
        print(json.dumps(mapping._solver_pool().submit(heavy_modules).result(timeout=120)))
    finally:
        mapping.close()
"""


def console_script_target(name: str) -> str:
    """``module:function`` of one of setup.py's console scripts."""
    import re
    from pathlib import Path

    setup = (Path(__file__).resolve().parents[1] / "setup.py").read_text()
    (target,) = re.findall(rf'"{name} = ([\w.]+:\w+)"', setup)
    return target


@pytest.mark.parametrize(("executable", "imports_torch"), [("odometry_node", False), ("trainer_node", False), (None, True)])
def test_the_solver_process_of_a_ros_executable_does_not_load_torch_or_rclpy(tmp_path, executable, imports_torch):
    """A spawned process first runs its parent's main script again, top-level imports included; an
    executable's script is ``from MODULE import FUNCTION`` (setup.py's console scripts), so the nodes'
    entry points must load nothing heavy, or the solver process loads it too (torch: 2.8 s more before
    the first solve, measured). The last case is a main script that imports torch: its solver does."""
    if executable is None:
        top_level_import = "import torch  # noqa: F401"
    else:
        module, function = console_script_target(executable).split(":")
        assert module == "nocal_ros.ros.entry_points"
        top_level_import = f"from {module} import {function}  # noqa: F401"
    script = tmp_path / "main_script.py"
    script.write_text(SOLVER_MODULES_SCRIPT.format(top_level_import=top_level_import))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == (["torch"] if imports_torch else [])
