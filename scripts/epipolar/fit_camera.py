"""Camera-only fit from arm-pose correspondences (no light field): how far the epipolar signal alone goes.

python scripts/epipolar/fit_camera.py BAG [--focal-steps N] [--full-steps N] [--lr LR] [--form raw] [--seed S]
"""
import argparse
import time

import torch

from nocal_ros.camera import CameraModel
from nocal_ros.data.bags import read_sequence
from nocal_ros.epipolar import arm_correspondences, calibrate_from_arm_poses, epipolar_loss
from nocal_ros.evaluation import calibration_errors

parser = argparse.ArgumentParser()
parser.add_argument("bag")
parser.add_argument("--focal-steps", type=int, default=300)
parser.add_argument("--full-steps", type=int, default=600)
parser.add_argument("--max-gap", type=int, default=8)
parser.add_argument("--lr", type=float, default=3e-3)
parser.add_argument("--form", default="centred")
parser.add_argument("--seed", type=int, default=0, help="seed of the distortion MLP's initialisation")
args = parser.parse_args()
torch.set_num_threads(1)
torch.manual_seed(args.seed)

sequence = read_sequence(args.bag)
truth = sequence.calibration
start = time.perf_counter()
corr = arm_correspondences(sequence.images, sequence.arm_poses, max_gap=args.max_gap)
print(f"{len(corr)} correspondences from {corr.pairs} pairs in {time.perf_counter() - start:.1f} s")
camera = CameraModel(truth.width, truth.height, distortion_form=args.form)


def report(label):
    e = calibration_errors(camera, truth)
    fx, fy, cx, cy = (float(v.detach()) for v in camera.intrinsics())
    print(f"{label}: fx {fx:.2f} fy {fy:.2f} cx {cx:.2f} cy {cy:.2f} focal {e['focal_error_percent']:.3f} % "
          f"pp {e['principal_point_error_px']:.2f} px dr {e['dr']:.5f} loss {float(epipolar_loss(camera, corr)):.4f}")


report("start")
camera.set_stage("focal")
start = time.perf_counter()
calibrate_from_arm_poses(camera, corr, steps=args.focal_steps, lr=args.lr)
report(f"focal ({time.perf_counter() - start:.1f} s)")
camera.set_stage("full")
start = time.perf_counter()
calibrate_from_arm_poses(camera, corr, steps=args.full_steps, lr=args.lr)
report(f"full ({time.perf_counter() - start:.1f} s)")
