"""PairDataset: labels against the closed form, gaps, labelled sampling, determinism, resizing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from nocal_ros.data.bags import read_sequence, write_sequence
from nocal_ros.data.pairs import PairDataset
from nocal_ros.data.sequence import FrameSequence
from nocal_ros.errors import ConfigError
from nocal_ros.geometry import make_transform, so3_exp


def make_sequence(n: int, labelled_frames, seed: int, size=(32, 24), name: str = "") -> FrameSequence:
    rng = np.random.default_rng(seed)
    width, height = size
    poses = np.stack([make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)])
    arm = np.full((n, 4, 4), np.nan)
    arm[list(labelled_frames)] = poses[list(labelled_frames)]
    images = rng.integers(0, 256, (n, height, width, 3), dtype=np.uint8)
    return FrameSequence(images, np.arange(n, dtype=np.int64) * 100_000_000, arm, poses, None, name=name)


def test_pairs_cover_gap_range_and_labels_match_closed_form():
    sequence = make_sequence(20, labelled_frames=[2, 3, 4, 5, 9, 15], seed=0)
    dataset = PairDataset([sequence], size=(16, 12), gap_range=(2, 5))
    assert len(dataset) == sum(20 - gap for gap in range(2, 6))
    batch = dataset.collate(torch.arange(len(dataset)))
    gaps = batch["gap"].numpy()
    assert set(gaps.tolist()) == {2, 3, 4, 5}
    np.testing.assert_array_equal(batch["index_j"] - batch["index_i"], batch["gap"])
    labelled_pairs = set()
    for k in range(len(dataset)):
        i, j = int(batch["index_i"][k]), int(batch["index_j"][k])
        if batch["labelled"][k]:
            labelled_pairs.add((i, j))
            expected = np.linalg.inv(sequence.arm_poses[i]) @ sequence.arm_poses[j]
            np.testing.assert_allclose(batch["T_ci_cj"][k].numpy(), expected, atol=1e-5)
        else:
            np.testing.assert_array_equal(batch["T_ci_cj"][k].numpy(), np.eye(4))
    assert labelled_pairs == {(2, 4), (2, 5), (3, 5), (4, 9), (5, 9)}
    assert batch["T_ci_cj"].dtype == torch.float32
    assert sorted(dataset.labelled_indices().tolist()) == torch.nonzero(batch["labelled"]).reshape(-1).tolist()


def test_items_are_resized_images_of_the_right_frames_and_camera():
    first = make_sequence(6, [0, 1], seed=1, size=(32, 24), name="a")
    second = make_sequence(5, [], seed=2, size=(20, 12), name="b")  # another camera, another size
    dataset = PairDataset([first, second], size=(16, 12), gap_range=(1, 2))
    assert len(dataset) == (5 + 4) + (4 + 3)
    for index in (0, len(dataset) - 1):
        item = dataset[index]
        sequence = (first, second)[int(item["camera_index"])]
        assert item["image_i"].shape == (3, 12, 16) and item["image_i"].dtype == torch.float32
        for key, frame in (("image_i", item["index_i"]), ("image_j", item["index_j"])):
            expected = cv2.resize(sequence.images[int(frame)], (16, 12), interpolation=cv2.INTER_AREA)
            np.testing.assert_allclose(item[key].permute(1, 2, 0).numpy(), expected / 255.0, atol=1e-7)
    assert int(dataset[len(dataset) - 1]["camera_index"]) == 1
    assert set(dataset.collate(torch.arange(len(dataset)))["camera_index"].tolist()) == {0, 1}


def test_labelled_sampling_and_hidden_labels():
    sequence = make_sequence(40, labelled_frames=range(10, 16), seed=3)
    dataset = PairDataset([sequence], size=(16, 12))
    generator = torch.Generator().manual_seed(0)
    labelled = dataset.sample(64, labelled=True, generator=generator)
    assert labelled["labelled"].all()
    i, j = labelled["index_i"].numpy(), labelled["index_j"].numpy()
    assert ((i >= 10) & (j <= 15)).all()
    for k in range(8):
        expected = np.linalg.inv(sequence.arm_poses[i[k]]) @ sequence.arm_poses[j[k]]
        np.testing.assert_allclose(labelled["T_ci_cj"][k].numpy(), expected, atol=1e-5)
    unlabelled = dataset.sample(64, labelled=False, generator=generator)
    assert not unlabelled["labelled"].any()
    np.testing.assert_array_equal(unlabelled["T_ci_cj"].numpy(), np.broadcast_to(np.eye(4), (64, 4, 4)))
    gaps = unlabelled["gap"]
    assert gaps.min() >= 1 and gaps.max() <= 8 and len(set(gaps.tolist())) > 4

    schedule = dataset.batches(2)
    assert [bool(next(schedule)["labelled"].all()) for _ in range(10)] == [False, False, False, False, True] * 2

    none = PairDataset([make_sequence(10, [0, 9], seed=4)], size=(16, 12), gap_range=(1, 8))
    assert len(none.labelled_indices()) == 0
    with pytest.raises(ConfigError, match="no labelled pairs"):
        none.sample(4, labelled=True)


def test_sampling_is_deterministic_given_a_seed():
    sequence = make_sequence(30, labelled_frames=range(0, 30, 2), seed=5)

    def draws(seed: int):
        dataset = PairDataset([sequence], size=(16, 12), seed=seed)
        stream = dataset.batches(4)
        return [next(stream) for _ in range(6)]

    first, again, other = draws(7), draws(7), draws(8)
    for a, b in zip(first, again):
        for key in a:
            assert torch.equal(a[key], b[key])
    assert any(not torch.equal(a["index_i"], b["index_i"]) for a, b in zip(first, other))


def test_bad_configuration():
    sequence = make_sequence(3, [], seed=6, name="short")
    with pytest.raises(ConfigError, match=r"no pairs with gap >= 4 \(frames per sequence: short: 3\)"):
        PairDataset([sequence], gap_range=(4, 8))
    with pytest.raises(ConfigError, match="gap_range"):
        PairDataset([sequence], gap_range=(0, 2))
    with pytest.raises(ConfigError, match="no sequences"):
        PairDataset([])


def test_bag_to_pairs(tmp_path):
    """The training data path end to end: a sequence through a real bag into labelled pairs."""
    sequence = make_sequence(12, labelled_frames=[1, 2, 3, 7], seed=9)
    back = read_sequence(write_sequence(sequence, tmp_path / "bag"))
    dataset = PairDataset([back], size=(16, 12), gap_range=(1, 4))
    pairs = dataset.collate(dataset.labelled_indices())
    got = sorted(zip(pairs["index_i"].tolist(), pairs["index_j"].tolist()))
    assert got == [(1, 2), (1, 3), (2, 3), (3, 7)]
    for k, (i, j) in enumerate(zip(pairs["index_i"].tolist(), pairs["index_j"].tolist())):
        expected = np.linalg.inv(sequence.arm_poses[i]) @ sequence.arm_poses[j]
        np.testing.assert_allclose(pairs["T_ci_cj"][k].numpy(), expected, atol=1e-5)
