"""Where the real recordings are (../shared/data/real/, README there), for the tests that read them.

They are never copied into the repository; a test that needs one skips, with the reason, where it is
missing.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
if not REAL.is_dir():
    REAL = Path("/work/shared/data/real")


def needs_real(name: str = "") -> pytest.MarkDecorator:
    """Skip unless ``REAL / name`` (the folder itself with no name) is present."""
    return pytest.mark.skipif(not (REAL / name).is_dir(), reason=f"real recordings not present at {REAL / name}")
