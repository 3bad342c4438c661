"""Train from the shipped model on a rendered non-4:3 camera with one input mapping, score on a held-out room.

The zero-shot comparison (measure.py) scores a pose head that never saw the camera; this one lets the
network learn the camera's frames under each mapping (encoder and hypernetwork train, the camera starts
at f = width), then scores on a held-out sequence of the same camera (test textures):

* the pose head's error on consecutive pairs (rotation deg, translation m, after the trainer's
  translation scale fit), and a "no motion" baseline;
* the photometric loss at the true pose through the learnt camera, over the network's pixels;
* the learnt focal's error (%).

python scripts/input_mapping/finetune.py --policy crop|stretch --size 496x150 [--steps 1500] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

import nocal_ros.camera
import nocal_ros.data.pairs
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.data.synthetic import random_calibration, render_sequence
from nocal_ros.evaluation import calibration_errors
from nocal_ros.training import train

from measure import mapping_for, score  # noqa: E402  (this folder)

parser = argparse.ArgumentParser()
parser.add_argument("--policy", choices=("crop", "stretch"), required=True)
parser.add_argument("--size", default="496x150")
parser.add_argument("--steps", type=int, default=1500)
parser.add_argument("--frames", type=int, default=200)
parser.add_argument("--seed", type=int, default=0)
parser.add_argument("--threads", type=int, default=1)
args = parser.parse_args()
torch.set_num_threads(args.threads)
size = tuple(int(v) for v in args.size.split("x"))
network = (80, 60)

# Route the training data and the camera's rays through the policy's map (whatever the core's is).
def policy_mapping(native, net):
    return mapping_for(args.policy, tuple(native), tuple(net))


def policy_input(image, net, out=None):
    mapping = policy_mapping((image.shape[1], image.shape[0]), net)
    return mapping.apply(image, out), mapping


nocal_ros.camera.input_mapping = policy_mapping
nocal_ros.data.pairs.network_input = policy_input

calibration = random_calibration(np.random.default_rng([args.seed, 11, size[0]]), *size)
training = render_sequence(calibration, args.frames, seed=200 + args.seed, split="train", labelled_fraction=0.3)
held_out = render_sequence(calibration, 60, seed=300 + args.seed, split="test", labelled_fraction=0.0)
config = {
    "seed": args.seed, "steps": args.steps, "curriculum": {"fixed": args.steps // 10, "focal": args.steps // 3},
    "learning_rates": {"encoder": 5e-5, "hypernetwork": 8e-5, "distortion": 1e-2, "intrinsics": 6.25e-3},
    "log_every": max(1, args.steps // 10), "checkpoint_every": 10**9,
}
start = time.perf_counter()
result = train(config, [training], init=load_checkpoint(None), device="cpu")
seconds = time.perf_counter() - start
model = result.model.eval()
camera = result.cameras[0].float64_copy().float()
scores = score(model, camera, held_out, mapping_for(args.policy, size, network))
errors = calibration_errors(result.cameras[0], calibration)
print(json.dumps({
    "policy": args.policy, "size": args.size, "steps": args.steps, "seed": args.seed, "train_s": round(seconds),
    "true_fx": round(float(calibration.K[0, 0]), 2), "learnt_fx": round(float(camera.K()[0, 0]), 2),
    "focal_error_percent": round(errors["focal_error_percent"], 2), "dr": round(errors["dr"], 5),
    "rot_err_deg": round(scores["rot_deg"], 3), "trans_err_m": round(scores["trans_m"], 4),
    "photometric": round(scores["photometric"], 5), "step_deg": round(scores["step_deg"], 3),
    "step_m": round(scores["step_m"], 4), "final_train_loss": round(result.history[-1]["loss"], 5),
}))
