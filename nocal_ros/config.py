"""Training configuration files: the one reader of a training YAML, for the CLI, the fine-tuning job
and the trainer node alike (the core imports it from here, never from ``nocal_ros.commands``).

What the keys mean and which values they take is :mod:`nocal_ros.training`'s business
(``training_config`` validates them); this module turns a file into a mapping, or into a
:class:`~nocal_ros.errors.ConfigError` that names the file and says what is wrong with it in one line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from nocal_ros.errors import ConfigError

#: A training recipe is a few dozen lines; anything this large is not one (and is not read into memory).
MAX_CONFIG_BYTES = 1 << 20


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """The YAML file as a dict; ConfigError naming the file when it is missing, binary or malformed."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(f"{path}: {size} bytes is too large for a training config (at most {MAX_CONFIG_BYTES})")
        text = path.read_bytes().decode("utf-8")
    except OSError as error:
        raise ConfigError(f"{path}: cannot read config ({error.strerror or error})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (not UTF-8), so not a YAML training config") from None
    try:
        config = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(error).split())})") from None
    except RecursionError:
        raise ConfigError(f"{path}: YAML nested too deeply to be a training config") from None
    if not isinstance(config, dict):
        raise ConfigError(f"{path}: config must be a mapping of training settings")
    return config
