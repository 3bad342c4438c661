"""Image pairs for training: every ``(i, j = i + gap)`` of one or more sequences, at the training size.

Each sequence is one camera (its index in the list is the pair's ``camera_index``, which selects the
camera model the trainer learns for it). Images are mapped to the training size once, at
construction, by :func:`nocal_ros.network_input.network_input` (the whole frame, ``cv2.INTER_AREA``:
the same map the camera's rays use, so any camera shape trains) and kept as one uint8 tensor per
sequence, so drawing a batch is indexing and one conversion to float, never a resize.

A pair is labelled when both frames have arm poses; its label is then
``T_ci_cj = inv(T_base_ci) @ T_base_cj`` (the pose head's target). Labelled frames are a small share of
a recording (the paper labels every 5th batch), so :meth:`PairDataset.labelled_indices` and
:meth:`PairDataset.sample` let a trainer ask for labelled pairs specifically.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import ConfigError
from nocal_ros.geometry import relative_transform
from nocal_ros.network_input import network_input


class PairDataset(Dataset):
    """All frame pairs ``(i, i + gap)``, ``gap`` in ``gap_range`` (inclusive), of the given sequences.

    Items are dicts: ``image_i``, ``image_j`` float32 ``(3, H, W)`` in [0, 1]; ``T_ci_cj`` float32
    ``(4, 4)`` (identity when unlabelled); ``labelled`` bool; ``camera_index`` int; ``gap`` int;
    plus ``index_i``, ``index_j`` (frame indices in their sequence).

    Args:
        sequences: one FrameSequence per camera.
        size: training ``(width, height)``.
        gap_range: smallest and largest frame gap. Indexing uniformly over the dataset draws gaps
            uniformly within the range wherever a sequence is long enough.
        labelled_every: the trainer's labelled-batch period, kept here for callers that build
            their schedule from the dataset (see :meth:`batches`).
        seed: seed of :meth:`batches`' default generator.
    """

    def __init__(
        self,
        sequences: Sequence[FrameSequence],
        size: tuple[int, int] = (80, 60),
        gap_range: tuple[int, int] = (1, 8),
        labelled_every: int = 5,
        seed: int = 0,
    ) -> None:
        width, height = (int(v) for v in size)
        low, high = (int(v) for v in gap_range)
        if width <= 0 or height <= 0:
            raise ConfigError(f"pair dataset: training size must be positive, got {size}")
        if not 1 <= low <= high:
            raise ConfigError(f"pair dataset: gap_range must satisfy 1 <= low <= high, got {gap_range}")
        if int(labelled_every) < 1:
            raise ConfigError(f"pair dataset: labelled_every must be at least 1, got {labelled_every}")
        if not sequences:
            raise ConfigError("pair dataset: no sequences given")
        self.size = (width, height)
        self.gap_range = (low, high)
        self.labelled_every = int(labelled_every)
        self.seed = int(seed)

        self.images: list[torch.Tensor] = []  # per sequence: (N, 3, H, W) uint8, resized once
        columns: dict[str, list[np.ndarray]] = {"camera": [], "i": [], "j": [], "labelled": [], "T": []}
        for camera_index, sequence in enumerate(sequences):
            self.images.append(_resized_tensor(sequence, width, height))
            n = len(sequence)
            labelled = sequence.labelled
            for gap in range(low, high + 1):
                i = np.arange(max(n - gap, 0))
                j = i + gap
                both = labelled[i] & labelled[j]
                T = np.broadcast_to(np.eye(4, dtype=np.float32), (len(i), 4, 4)).copy()
                for row in np.flatnonzero(both):
                    T[row] = relative_transform(sequence.arm_poses[i[row]], sequence.arm_poses[j[row]])
                columns["camera"].append(np.full(len(i), camera_index))
                columns["i"].append(i)
                columns["j"].append(j)
                columns["labelled"].append(both)
                columns["T"].append(T)
        self.camera_index = torch.from_numpy(np.concatenate(columns["camera"]).astype(np.int64))
        self.index_i = torch.from_numpy(np.concatenate(columns["i"]).astype(np.int64))
        self.index_j = torch.from_numpy(np.concatenate(columns["j"]).astype(np.int64))
        self.labelled = torch.from_numpy(np.concatenate(columns["labelled"]).astype(bool))
        self.T_ci_cj = torch.from_numpy(np.concatenate(columns["T"]).astype(np.float32))
        if len(self.index_i) == 0:
            lengths = ", ".join(f"{s.name or k}: {len(s)}" for k, s in enumerate(sequences))
            raise ConfigError(f"pair dataset: no pairs with gap >= {low} (frames per sequence: {lengths})")
        self._labelled_indices = torch.nonzero(self.labelled).reshape(-1)

    def __len__(self) -> int:
        return len(self.index_i)

    def labelled_indices(self) -> torch.Tensor:
        """Indices of the pairs whose ``T_ci_cj`` is known."""
        return self._labelled_indices

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {key: value[0] for key, value in self.collate(torch.tensor([int(index)])).items()}

    def collate(self, indices: torch.Tensor | Sequence[int]) -> dict[str, torch.Tensor]:
        """A batch of pairs by dataset index, as stacked tensors (one gather per sequence)."""
        indices = torch.as_tensor(indices, dtype=torch.long).reshape(-1)
        if len(indices) and (int(indices.min()) < -len(self) or int(indices.max()) >= len(self)):
            raise IndexError(f"pair index out of range for {len(self)} pairs")
        indices = indices % len(self)
        camera = self.camera_index[indices]
        index_i, index_j = self.index_i[indices], self.index_j[indices]
        width, height = self.size
        image_i = torch.empty((len(indices), 3, height, width), dtype=torch.uint8)
        image_j = torch.empty_like(image_i)
        for camera_index in torch.unique(camera).tolist():
            rows = camera == camera_index
            image_i[rows] = self.images[camera_index][index_i[rows]]
            image_j[rows] = self.images[camera_index][index_j[rows]]
        return {
            "image_i": image_i.float().div_(255.0),
            "image_j": image_j.float().div_(255.0),
            "T_ci_cj": self.T_ci_cj[indices],
            "labelled": self.labelled[indices],
            "camera_index": camera,
            "gap": index_j - index_i,
            "index_i": index_i,
            "index_j": index_j,
        }

    def sample(self, batch_size: int, labelled: bool, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """A random batch (with replacement): labelled pairs only, or any pairs with labels hidden.

        Unlabelled batches mark every pair ``labelled = False`` and give identity ``T_ci_cj``, so a
        loss cannot use a label by accident: they train by rendering alone, as in the paper.

        Raises:
            ConfigError: labelled pairs were asked for and there are none.
        """
        if labelled:
            pool = self._labelled_indices
            if len(pool) == 0:
                raise ConfigError(
                    f"pair dataset: no labelled pairs (no two frames with arm poses within gaps {self.gap_range})"
                )
            indices = pool[torch.randint(len(pool), (batch_size,), generator=generator)]
            return self.collate(indices)
        batch = self.collate(torch.randint(len(self), (batch_size,), generator=generator))
        batch["labelled"] = torch.zeros_like(batch["labelled"])
        batch["T_ci_cj"] = torch.eye(4).expand(batch_size, 4, 4).clone()
        return batch

    def batches(self, batch_size: int, generator: torch.Generator | None = None):
        """Endless batches; every ``labelled_every``-th is labelled when labelled pairs exist."""
        generator = generator if generator is not None else torch.Generator().manual_seed(self.seed)
        count = 0
        while True:
            count += 1
            labelled = count % self.labelled_every == 0 and len(self._labelled_indices) > 0
            yield self.sample(batch_size, labelled, generator)


def _resized_tensor(sequence: FrameSequence, width: int, height: int) -> torch.Tensor:
    """``(N, 3, H, W)`` uint8 at the training size, each frame mapped by :func:`network_input` (the
    camera's rays use the same map, whatever the camera's aspect ratio)."""
    images = sequence.images
    if (images.shape[2], images.shape[1]) != (width, height):
        resized = np.empty((len(images), height, width, images.shape[3]), dtype=np.uint8)
        for index, image in enumerate(images):
            network_input(image, (width, height), out=resized[index])
        images = resized
    return torch.from_numpy(np.ascontiguousarray(images.transpose(0, 3, 1, 2)))
