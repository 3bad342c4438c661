"""``nocal train --out`` onto a directory that holds a run: refused unless ``--resume`` or ``--overwrite``."""

from __future__ import annotations

import hashlib
from pathlib import Path

from nocal_ros.cli import main

REPO = Path(__file__).resolve().parents[1]
TINY_RECIPE = REPO / "config" / "tiny.yaml"


def digests(directory: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir()) if p.is_file()}


def train(out: Path, *extra: str) -> int:
    return main(["train", "--config", str(TINY_RECIPE), "--out", str(out), "--threads", "1", "--steps", "5", *extra])


def test_a_finished_run_is_kept_unless_resume_or_overwrite(tmp_path, capsys):
    from nocal_ros.checkpoint import load_checkpoint

    out = tmp_path / "run"
    assert train(out, "--seed", "1") == 0
    finished = digests(out)
    assert {"model.safetensors", "last.safetensors", "metrics.csv"} <= set(finished)
    capsys.readouterr()

    assert train(out, "--seed", "2") == 1  # the issue: this silently replaced both checkpoints and truncated metrics.csv
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and "already holds a training run" in err and "--overwrite" in err
    assert digests(out) == finished

    assert train(out, "--seed", "2", "--resume", "--overwrite") == 1
    assert "not both" in capsys.readouterr().err and digests(out) == finished

    assert train(out, "--resume", "--steps", "7") == 0  # --steps after the default: 7 wins
    assert load_checkpoint(out / "last.safetensors").training["step"] == 7
    assert len((out / "metrics.csv").read_text().splitlines()) == 1 + 2  # header, the rows of steps 5 and 7

    assert train(out, "--seed", "2", "--overwrite") == 0
    replaced = load_checkpoint(out / "last.safetensors")
    assert replaced.training["step"] == 5 and replaced.metadata["config"]["seed"] == 2
    assert len((out / "metrics.csv").read_text().splitlines()) == 1 + 1  # a new run's metrics only


def test_overwrite_is_refused_for_fine_tuning(tmp_path, capsys):
    assert main(["train", "--init", "--bag", str(tmp_path / "b.mcap"), "--out", str(tmp_path / "store"), "--overwrite"]) == 1
    assert "never replaces one" in capsys.readouterr().err
