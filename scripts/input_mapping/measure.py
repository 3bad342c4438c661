"""Which mapping of a non-4:3 frame onto the network's 4:3 input works best: crop, stretch or pad?

For rendered sequences of random cameras of several shapes (held-out test textures), each mapping is
scored with the shipped model (or --model):

* the pose head's error on consecutive pairs (rotation in degrees, translation in metres) against the
  ground truth, as the odometry runs it;
* the photometric loss (MSE, colours in [0, 1]) of both views rendered at the true relative pose
  through the true camera (``CameraModel.from_calibration``), over the network pixels that show the
  scene (padding excluded), as training computes it.

Stretch is the core's mapping (``nocal_ros.network_input``, chosen by these measurements); crop and
pad are built here.

python scripts/input_mapping/measure.py [--frames 40] [--seeds 4] [--model M] [--threads 1]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch

from nocal_ros.camera import CameraModel, pixel_grid
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.data.synthetic import random_calibration, render_sequence
from nocal_ros.geometry import relative_transform, rotation_angle_deg
from nocal_ros.network_input import InputMapping, input_mapping

SHAPES = {"3.3:1 (KITTI)": (496, 150), "16:9": (384, 216), "5:4": (300, 240), "4:3 (control)": (320, 240)}


def mapping_for(policy: str, native: tuple[int, int], network: tuple[int, int]) -> InputMapping:
    W, H = native
    w, h = network
    if policy == "crop":  # the largest centred window of the network's aspect, whole pixels
        if W * h > H * w:
            width = min(W, int(round(H * w / h)))
            return InputMapping(native, network, ((W - width) // 2, 0, width, H))
        height = min(H, int(round(W * h / w)))
        return InputMapping(native, network, (0, (H - height) // 2, W, height))
    if policy == "stretch":  # the whole frame: the core's map (nocal_ros.network_input.input_mapping)
        assert input_mapping(native, network).window == (0, 0, W, H)
        return InputMapping(native, network, (0, 0, W, H))
    if policy == "pad":  # the smallest centred window of the network's aspect that holds the frame
        if W * h > H * w:
            height = int(round(W * h / w))
            return InputMapping(native, network, (0, -((height - H) // 2), W, height))
        width = int(round(H * w / h))
        return InputMapping(native, network, (-((width - W) // 2), 0, width, H))
    raise ValueError(policy)


def apply(mapping: InputMapping, image: np.ndarray) -> np.ndarray:
    x0, y0, width, height = mapping.window
    W, H = mapping.native_size
    if x0 >= 0 and y0 >= 0 and x0 + width <= W and y0 + height <= H:
        return mapping.apply(image)
    top, left = -min(y0, 0), -min(x0, 0)
    padded = cv2.copyMakeBorder(image, top, height - H - top, left, width - W - left, cv2.BORDER_CONSTANT, value=0)
    return cv2.resize(padded, mapping.network_size, interpolation=cv2.INTER_AREA)


def valid_pixels(mapping: InputMapping) -> torch.Tensor:
    """Network pixels whose area lies inside the native image (all of them but for padding)."""
    w, h = mapping.network_size
    u, v = pixel_grid(w, h, dtype=torch.float64)
    sx, sy = mapping.scale
    un, vn = mapping.to_native(u, v)
    W, H = mapping.native_size
    inside = (un - sx / 2 >= -0.5 - 1e-9) & (un + sx / 2 <= W - 0.5 + 1e-9)
    inside &= (vn - sy / 2 >= -0.5 - 1e-9) & (vn + sy / 2 <= H - 0.5 + 1e-9)
    return torch.nonzero(inside).reshape(-1)


@torch.no_grad()
def score(model, camera: CameraModel, sequence, mapping: InputMapping) -> dict[str, float]:
    images = np.stack([apply(mapping, image) for image in sequence.images])
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
    truth = np.stack([relative_transform(a, b) for a, b in zip(sequence.ground_truth[:-1], sequence.ground_truth[1:])])
    T_pred = model.predict_pose(x[:-1], x[1:]).double().numpy()
    rotation = [rotation_angle_deg(p[:3, :3].T @ t[:3, :3]) for p, t in zip(T_pred, truth)]
    translation = np.linalg.norm(T_pred[:, :3, 3] - truth[:, :3, 3], axis=1)

    # Photometric loss at the true pose through the true camera, over the pixels that show the scene.
    index = valid_pixels(mapping)
    w, h = mapping.network_size
    u, v = pixel_grid(w, h, dtype=torch.float32)
    directions = camera.pixel_rays(*mapping.to_native(u, v))[index]
    from nocal_ros.geometry import pluecker_from_rays, rays_camera_to_world

    _, z = model.encode(x[:-1], x[1:])
    T_j = torch.from_numpy(truth).float()
    identity = torch.eye(4).expand(len(T_j), 4, 4)
    errors = []
    for T, image in ((identity, x[:-1]), (T_j, x[1:])):
        origins, world = rays_camera_to_world(directions.expand(len(T), -1, -1), T)
        rendered = model.render(z, pluecker_from_rays(origins, world))
        target = image.flatten(2)[:, :, index].transpose(1, 2)
        errors.append((rendered - target).square().mean().item())
    return {"rot_deg": float(np.mean(rotation)), "trans_m": float(np.mean(translation)),
            "photometric": float(np.mean(errors)), "valid_share": len(index) / (w * h),
            "step_deg": float(np.mean([rotation_angle_deg(t[:3, :3]) for t in truth])),
            "step_m": float(np.mean(np.linalg.norm(truth[:, :3, 3], axis=1)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    checkpoint = load_checkpoint(args.model)
    model = checkpoint.model.eval()
    network = tuple(checkpoint.metadata.get("training_resolution") or (80, 60))
    print(f"model {checkpoint.path or 'shipped default'}, network input {network[0]}x{network[1]}, "
          f"{args.seeds} seeds x {args.frames} frames per shape, test textures")
    policies = ("crop", "stretch", "pad")
    start = time.perf_counter()
    for name, size in SHAPES.items():
        results = {policy: [] for policy in policies}
        for seed in range(args.seeds):
            calibration = random_calibration(np.random.default_rng([seed, 11, size[0]]), *size)
            sequence = render_sequence(calibration, args.frames, seed=100 + seed, split="test", labelled_fraction=0.0)
            camera = CameraModel.from_calibration(calibration)
            for policy in policies:
                results[policy].append(score(model, camera, sequence, mapping_for(policy, size, network)))
        print(f"\n{name} {size[0]}x{size[1]}: mean step {np.mean([r['step_m'] for r in results['crop']]):.4f} m, "
              f"{np.mean([r['step_deg'] for r in results['crop']]):.3f} deg")
        print(f"  {'mapping':8s} {'rot err deg':>12s} {'trans err m':>12s} {'photometric':>12s} {'scene px':>9s}")
        for policy in policies:
            rows = results[policy]
            mean = {key: float(np.mean([r[key] for r in rows])) for key in rows[0]}
            print(f"  {policy:8s} {mean['rot_deg']:12.3f} {mean['trans_m']:12.4f} {mean['photometric']:12.5f} "
                  f"{100 * mean['valid_share']:8.0f}%")
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
