"""Local mapping's worker process: solves run there, and a process that dies is replaced."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest
from test_camera_initialisation import noisy_window, problem_through

from nocal_ros.odometry.calibration import OnlineCamera
from nocal_ros.odometry.local_mapping import SOLVER_RESTARTS, LocalMapping


def test_a_solver_process_that_died_is_replaced_and_the_solve_still_runs():
    """The solver process killed (as the out-of-memory killer would) between two solves: the next solve
    starts a new process, gives the same answer as before, and says so in ``solver_restarts``; a
    process killed after the last restart allowed fails the solve."""
    camera, poses, points, keyframe_index, point_index, pixels = noisy_window(3)
    problem = problem_through(camera, poses, points, keyframe_index, point_index, pixels)
    mapping = LocalMapping(OnlineCamera(camera, "file"), synchronous=False)
    try:
        first = mapping._solve(problem)
        (pid,) = list(mapping._solver._processes)
        os.kill(pid, signal.SIGKILL)
        again = mapping._solve(problem)
        assert first.success and again.success
        np.testing.assert_allclose(again.poses, first.poses, atol=1e-12)
        assert mapping.solver_restarts == 1
        assert pid not in mapping._solver._processes
        # One that keeps dying is not replaced for ever: past SOLVER_RESTARTS the solve fails.
        mapping.solver_restarts = SOLVER_RESTARTS
        (pid,) = list(mapping._solver._processes)
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(BrokenProcessPool):
            mapping._solve(problem)
    finally:
        mapping.close()


def test_the_solver_process_loads_its_modules_before_the_first_solve_and_never_torch():
    """The solver process's start imports the solver and the camera initialisation, and neither loads
    torch: loaded at the first camera initialisation of a live stream, torch took 1.5 s of it."""
    code = ("import json, sys\n"
            "from nocal_ros.odometry.local_mapping import _import_solver\n"
            "_import_solver()\n"
            "print(json.dumps(sorted(m for m in ('torch', 'cv2', 'scipy.sparse', 'nocal_ros.odometry.camera_initialisation') if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120).stdout
    assert json.loads(out) == ["cv2", "nocal_ros.odometry.camera_initialisation", "scipy.sparse"]
