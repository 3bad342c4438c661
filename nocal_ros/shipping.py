"""Turn a pretraining run into the shipped default model.

``python -m nocal_ros.shipping runs/pretrain/model.safetensors`` writes
``nocal_ros/models/default.safetensors`` (+ sidecar). What changes on the way:

* The cameras learnt during pretraining belong to the rendered pretraining cameras, not to the
  user's, so the shipped model carries one *prior* camera instead: f = image width, centred
  principal point, no distortion (the paper's starting point). Until the user fine-tunes, that is
  the honest CameraInfo; ``camera_is_prior`` in the metadata says so.
* The pose head's error is measured on held-out rendered sequences (test-split rooms and textures,
  cameras drawn like the pretraining ones) and stored as ``pose_error_std``, from which the
  odometry estimator derives its covariance.
* Optimiser state is dropped: the file holds inference weights only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nocal_ros import geometry
from nocal_ros.camera import CameraModel
from nocal_ros.checkpoint import DEFAULT_MODEL_PATH, Checkpoint, load_checkpoint, save_checkpoint
from nocal_ros.data.pairs import PairDataset
from nocal_ros.data.sequence import FrameSequence

PRIOR_CAMERA_SIZE = (640, 480)


def training_size(checkpoint: Checkpoint) -> tuple[int, int]:
    """The ``(width, height)`` the model was trained at."""
    size = checkpoint.metadata.get("training_resolution") or (checkpoint.metadata.get("config") or {}).get("image_size")
    if not size:
        raise ValueError(f"{checkpoint.path}: sidecar has no training resolution")
    return int(size[0]), int(size[1])


@torch.no_grad()
def pose_errors(checkpoint: Checkpoint, sequences: list[FrameSequence], gap: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair pose-head errors on consecutive frames ``gap`` apart, against ground truth.

    Returns ``(translation_errors (P, 3) metres, rotation_errors (P, 3) rotation vectors, radians)``,
    both in the first camera's frame: the error ``inv(T_true) @ T_pred`` of each pair.
    """
    width, height = training_size(checkpoint)
    model = checkpoint.model.eval()
    translation, rotation = [], []
    for sequence in sequences:
        truth = FrameSequence(sequence.images, sequence.stamps_ns, sequence.ground_truth, name=sequence.name)
        dataset = PairDataset([truth], size=(width, height), gap_range=(gap, gap))
        batch = dataset.collate(np.arange(len(dataset)))
        predicted = model.predict_pose(batch["image_i"], batch["image_j"]).double().numpy()
        for T_pred, T_true in zip(predicted, batch["T_ci_cj"].double().numpy()):
            error = geometry.invert_transform(T_true) @ T_pred
            translation.append(error[:3, 3])
            rotation.append(geometry.so3_log(error[:3, :3]))
    return np.asarray(translation), np.asarray(rotation)


def pose_error_std(translation_errors: np.ndarray, rotation_errors: np.ndarray) -> dict[str, float]:
    """Isotropic per-axis standard deviations (RMS over pairs and axes), as the estimator's covariance model uses."""
    return {
        "translation_m": float(np.sqrt(np.mean(translation_errors**2))),
        "rotation_rad": float(np.sqrt(np.mean(rotation_errors**2))),
    }


def validation_sequences(count: int, frames: int, seed: int, size: tuple[int, int]) -> list[FrameSequence]:
    """Held-out rendered sequences: test-split rooms and textures, cameras drawn like pretraining's."""
    from nocal_ros.data.synthetic import random_calibration, render_sequence

    rng = np.random.default_rng(seed)
    return [
        render_sequence(random_calibration(rng, *size), frames, seed=seed * 1000 + index, split="test", labelled_fraction=0.0)
        for index in range(count)
    ]


def package_model(
    source: str | Path,
    destination: str | Path = DEFAULT_MODEL_PATH,
    sequences: list[FrameSequence] | None = None,
    prior_size: tuple[int, int] = PRIOR_CAMERA_SIZE,
) -> dict[str, Any]:
    """Write the shipped model from a trained checkpoint; returns the facts added to its metadata."""
    checkpoint = load_checkpoint(source)
    sequences = sequences if sequences is not None else validation_sequences(4, 60, seed=7, size=(160, 120))
    translation, rotation = pose_errors(checkpoint, sequences)
    facts = {
        "pose_error_std": pose_error_std(translation, rotation),
        "pose_error_validation": {
            "pairs": len(translation),
            "sequences": [s.name for s in sequences],
            "frame_gap": 1,
            "translation_rmse_m": float(np.sqrt(np.mean(np.sum(translation**2, axis=1)))),
            "rotation_rmse_deg": float(np.degrees(np.sqrt(np.mean(np.sum(rotation**2, axis=1))))),
        },
        "camera_is_prior": True,
        "source_checkpoint": str(Path(source).name),
        "source_weights_sha256": checkpoint.metadata.get("weights_sha256"),
    }
    metadata = dict(checkpoint.metadata.get("metadata") or {})
    metadata.update(facts)
    metadata["training_resolution"] = list(training_size(checkpoint))
    metadata["config"] = checkpoint.metadata.get("config")
    prior = CameraModel(*prior_size)  # f = width, centred principal point, zero distortion
    save_checkpoint(destination, checkpoint.model, [prior], metadata)
    return facts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nocal_ros.shipping", description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="trained checkpoint, e.g. runs/pretrain/model.safetensors")
    parser.add_argument("--out", default=str(DEFAULT_MODEL_PATH), help="where to write the shipped model")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    facts = package_model(args.source, args.out)
    validation = facts["pose_error_validation"]
    print(f"wrote {args.out}: pose error on {validation['pairs']} held-out pairs: "
          f"translation RMSE {validation['translation_rmse_m'] * 100:.2f} cm, rotation RMSE {validation['rotation_rmse_deg']:.2f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
