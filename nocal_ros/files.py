"""Writing files so that a crash, a kill or a full disk never leaves half a file under a real name.

Every output of the package (checkpoints, reports, trajectories, calibrations, plots) is written to a
temporary name in its destination directory, flushed to disk, and moved into place with
``os.replace`` (atomic on POSIX and Windows). When anything fails on the way (``ENOSPC`` included),
the temporary file is removed and the destination keeps what it held before.

``pause_point`` is a test hook: when the environment variable ``NOCAL_<SCOPE>_PAUSE_AT`` names a point
of a commit sequence, the writer creates the file named by ``NOCAL_<SCOPE>_PAUSE_FILE`` and sleeps
there, so a test can SIGKILL a real process at a known moment instead of racing it. It costs one
environment lookup per call.
"""

from __future__ import annotations

import contextlib
import os
import time
import uuid
from collections.abc import Iterator
from pathlib import Path


def pause_point(scope: str, name: str) -> None:
    """Hold the process here, forever, when ``NOCAL_<scope>_PAUSE_AT`` is ``name`` (tests kill it)."""
    if os.environ.get(f"NOCAL_{scope}_PAUSE_AT") != name:
        return
    signal_file = os.environ.get(f"NOCAL_{scope}_PAUSE_FILE")
    if signal_file:
        Path(signal_file).write_text(name)
    while True:  # the test kills us here
        time.sleep(0.05)


def fsync_dir(path: str | os.PathLike) -> None:
    """Make renames in directory ``path`` durable (POSIX; Windows cannot open directories, nor needs to)."""
    if os.name != "posix":
        return
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def temporary_name(path: Path) -> Path:
    """A hidden name beside ``path``, unique to this writer: ``.<name>.<pid>.<random>.tmp``."""
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")


def pid_alive(pid: int) -> bool:
    """True when process ``pid`` exists (a zombie counts as gone)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return False
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as handle:
            return handle.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the :func:`temporary_name` files of ``path`` whose writer process is gone (killed mid-write)."""
    removed = []
    for candidate in path.parent.glob(f".{path.name}.*.tmp"):
        pid_text = candidate.name[len(path.name) + 2:].split(".", 1)[0]
        if pid_text.isdigit() and int(pid_text) != os.getpid() and not pid_alive(int(pid_text)):
            with contextlib.suppress(OSError):
                candidate.unlink()
                removed.append(candidate)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s content to; on a clean exit it is fsynced and moved
    onto ``path``, on any exception it is removed and ``path`` is left as it was.

    For writers that want a file name (``matplotlib.savefig``, YAML dumpers, ``cv2.imwrite``).
    """
    path = Path(path)
    temporary = temporary_name(path)
    try:
        yield temporary
        with open(temporary, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        with contextlib.suppress(OSError):
            temporary.unlink()
    fsync_dir(path.parent)


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically; see :func:`atomic_path`."""
    path = Path(path)
    with atomic_path(path) as temporary:
        with open(temporary, "wb") as handle:
            handle.write(data.encode("utf-8") if isinstance(data, str) else data)
            handle.flush()
    return path
