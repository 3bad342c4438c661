"""Argument types shared by the ``nocal`` subcommands: each refuses a bad value at parse time.

Used as ``argparse`` ``type=`` functions, so ``--threads -1``, ``--fps nan`` or ``--device bogus`` end
in argparse's one-line error naming the option (``nocal_ros.cli`` prints it without the usage block)
before anything is loaded, instead of a traceback or a silently odd run later. One module, so that
``--threads`` or ``--max-frames`` mean the same in every command.
"""

from __future__ import annotations

import argparse
import math

ArgumentTypeError = argparse.ArgumentTypeError


def _number(text: str, kind: type) -> int | float:
    try:
        return kind(text)
    except (TypeError, ValueError):
        name = "an integer" if kind is int else "a number"
        raise ArgumentTypeError(f"expected {name}, got {text!r}") from None


def finite_float(text: str) -> float:
    """Any finite number (not nan, inf)."""
    value = _number(text, float)
    if not math.isfinite(value):
        raise ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number above zero (a rate, a period, a tolerance)."""
    value = finite_float(text)
    if value <= 0:
        raise ArgumentTypeError(f"expected a number above 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number of zero or more (a speed)."""
    value = finite_float(text)
    if value < 0:
        raise ArgumentTypeError(f"expected a number of 0 or more, got {text!r}")
    return value


def fraction(text: str) -> float:
    """A finite number in [0, 1]."""
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise ArgumentTypeError(f"expected a fraction between 0 and 1, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer of 1 or more (a count of frames, steps, a batch size)."""
    value = _number(text, int)
    if value < 1:
        raise ArgumentTypeError(f"expected an integer of 1 or more, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer of 0 or more (a seed, an index, ``--keep`` where 0 means all)."""
    value = _number(text, int)
    if value < 0:
        raise ArgumentTypeError(f"expected an integer of 0 or more, got {text!r}")
    return value


def thread_count(text: str) -> int:
    """torch CPU threads: 1 or more, or 0 for torch's default."""
    value = _number(text, int)
    if value < 0:
        raise ArgumentTypeError(f"expected a thread count of 1 or more (0: torch's default), got {text!r}")
    return value


def image_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT``, each at least 8 pixels."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise ArgumentTypeError(f"size must look like 160x120, got {text!r}") from None
    if width < 8 or height < 8:
        raise ArgumentTypeError(f"size must be at least 8x8, got {text!r}")
    return width, height


def device_name(text: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (``mps`` where torch has it), checked against this machine.

    Returned as given: each command resolves ``auto`` itself.
    """
    text = text.strip()
    if text == "auto":
        return text
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise ArgumentTypeError(f"unknown device {text!r}; use auto, cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ArgumentTypeError(f"device {text!r} requested but CUDA is not available on this machine")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ArgumentTypeError(f"device {text!r} requested but this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif device.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            raise ArgumentTypeError(f"device {text!r} requested but MPS is not available on this machine")
    elif device.type != "cpu":
        raise ArgumentTypeError(f"unsupported device {text!r}; use auto, cpu, cuda or cuda:N")
    return text


def device_list(text: str) -> str:
    """``auto`` or a comma list of :func:`device_name` values (``cpu,cuda``)."""
    if text.strip() == "auto":
        return "auto"
    names = [name.strip() for name in text.split(",")]
    if not all(names) or "auto" in names:
        raise ArgumentTypeError(f"expected auto or a comma list such as cpu,cuda, got {text!r}")
    for name in names:
        device_name(name)
    return ",".join(names)
