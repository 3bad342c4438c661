"""Replay a bag's images in real time through the estimator as the odometry node runs it, and score it.

    python scripts/compare/realtime.py BAG [--rate HZ] [--calibration YAML] [--camera-height M]

The node's way: a one-slot mailbox (a frame that arrives while another is being processed replaces the
waiting one and is counted as dropped), a worker thread that processes the newest frame, and local
mapping in its own thread and process (``nocal odometry`` maps synchronously instead, so that a
replay repeats exactly). Prints the frames processed and dropped, the worker thread's CPU time per
frame, the online camera's errors, and the RPE over consecutive processed frames and APE Sim(3)
against the bag's ground truth, and the online camera's state (with the check of a given calibration,
``--calibration``, as the node's ``camera_info_url`` gives one). With ``--camera-height`` (the node's
``camera_height``) it also prints the frames per scale source and the APE without a scale correction.
Runs differ from run to run: they depend on the machine's timing.
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("bag")
    parser.add_argument("--rate", type=float, default=0.0, help="frames per second (default: the bag's stamps)")
    parser.add_argument("--arm-topic", default="", help="arm poses (PoseStamped) for metric scale; '' to ignore")
    parser.add_argument("--calibration", help="camera_calibration YAML to start the online camera from")
    parser.add_argument("--camera-height", type=float, help="the camera's height above the ground (m), for metric scale")
    args = parser.parse_args(argv)

    import torch

    from nocal_ros import evaluation
    from nocal_ros.data.bags import read_pose_messages, read_sequence
    from nocal_ros.geometry import invert_transform
    from nocal_ros.lens import CameraCalibration
    from nocal_ros.odometry import OdometryEstimator, replay_at_rate

    torch.set_num_threads(1)
    sequence = read_sequence(args.bag, pose_source="none")
    stamps = np.asarray(sequence.stamps_ns, dtype=np.int64)
    rate = args.rate or 1e9 / float(np.median(np.diff(stamps)))
    arm_stamps, arm_poses = read_pose_messages(args.bag, args.arm_topic) if args.arm_topic else ([], [])
    estimator = OdometryEstimator(calibration=CameraCalibration.load(args.calibration) if args.calibration else None,
                                  camera_height=args.camera_height)
    poses: dict[int, np.ndarray] = {}
    sources: dict[str, int] = {}
    next_arm = 0

    def handle(k: int, image: np.ndarray) -> None:
        nonlocal next_arm
        while next_arm < len(arm_stamps) and arm_stamps[next_arm] <= stamps[k]:
            estimator.add_arm_pose(int(arm_stamps[next_arm]), arm_poses[next_arm])
            next_arm += 1
        result = estimator.process(int(stamps[k]), image)
        if result is not None:
            poses[k] = result.T_odom_cam
            sources[result.scale_source] = sources.get(result.scale_source, 0) + 1

    replay = replay_at_rate(sequence.images, rate, handle)
    estimator.wait_for_mapping(timeout=60.0)
    frames = sorted(poses)
    truth = sequence.ground_truth[frames]
    estimate = np.array([poses[k] for k in frames])
    truth = invert_transform(truth[0]) @ truth
    camera = evaluation.calibration_errors(estimator.camera_info()[0], sequence.calibration)
    rpe = evaluation.relative_pose_error(estimate, truth)
    ape = evaluation.absolute_pose_error(estimate, truth, correct_scale=True)
    print(f"{args.bag} at {rate:g} Hz: {len(frames)} of {len(stamps)} frames processed, {replay.dropped} dropped "
          f"(worker CPU per frame: median {np.median(replay.cpu_ms):.1f} ms, mean {np.mean(replay.cpu_ms):.1f} ms); "
          f"focal {camera['focal_error_percent']:.2f} %, dr {camera['dr']:.4f}; RPE over processed pairs "
          f"{rpe['translation_m']['rmse']:.4f} m / {rpe['rotation_deg']['rmse']:.3f} deg; APE Sim(3) {ape['rmse']:.4f} m "
          f"(scale {ape['scale']:.3f}); {len(estimator.timings()['bundle_adjustment'])} bundle adjustments for "
          f"{estimator.counters.keyframes} keyframes")
    status = estimator.calibration_status()
    checks = [f"{kind} calibration {status[kind + '_check']}" for kind in ("given", "carried") if status.get(kind + "_check")]
    print(f"camera: {status['state']} ({status['source']})" + "".join(f"; {check}" for check in checks))
    if args.camera_height is not None:
        metric = evaluation.absolute_pose_error(estimate, truth, correct_scale=False)
        print(f"scale sources (frames): {dict(sorted(sources.items()))}; APE SE(3) {metric['rmse']:.4f} m")
    estimator.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
