"""A directory of versioned models with an atomic ``latest`` pointer.

A fine-tuning run must never leave a robot without a loadable model: a crash, a cancel, an
out-of-memory kill or a power cut at any moment has to leave the previous model in place. The store
gets there with the usual rename tricks and nothing else::

    store/
      v0001/               model.safetensors, model.json (checkpoint sidecar), version.json
      v0002/
      latest.json          {"version": "v0002", "model": "model.safetensors", ...}
      .staging-<pid>-<id>/ a version being written (removed if its writer died)

1. A new version is written into a ``.staging-*`` directory, every file is fsynced, and a
   ``version.json`` manifest (file sizes and SHA-256) is written last.
2. The staging directory is renamed to the next free ``vNNNN`` name (``rename`` of a directory is
   atomic; it fails rather than overwrites if another writer took the name first).
3. ``latest.json`` is written under a temporary name, fsynced, and moved over the old pointer with
   ``os.replace``, which is atomic on POSIX and Windows.

The pointer is a small JSON file rather than a symlink because symlinks need privileges on Windows, are
not carried by some volume mounts and archive tools, and a file can carry the version's checksum. A
reader therefore sees either the old pointer or the new one, and both name complete versions.

``resolve_model_path`` is the one place that turns what a user passes as a model (a ``.safetensors``
file, a version directory, or a store directory) into a checkpoint file; the checkpoint loader and the
odometry node call it, so pointing ``model_path`` at a store makes a node follow its newest model.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from nocal_ros.errors import CheckpointError
from nocal_ros.files import pause_point, pid_alive

log = logging.getLogger(__name__)

POINTER_NAME = "latest.json"
MANIFEST_NAME = "version.json"
MODEL_NAME = "model.safetensors"
STAGING_PREFIX = ".staging-"
FORMAT_VERSION = 1
_VERSION_RE = re.compile(r"^v(\d{4,})$")

# Test hook (nocal_ros.files.pause_point): when NOCAL_STORE_PAUSE_AT names one of these points of the
# commit sequence, the writer creates the file named by NOCAL_STORE_PAUSE_FILE and sleeps there, so a
# test can SIGKILL a real process at a known moment instead of racing it.
PAUSE_POINTS = ("staging-written", "manifest-written", "version-renamed", "pointer-tmp-written")


def _pause_point(name: str) -> None:
    pause_point("STORE", name)


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as handle:
        os.fsync(handle.fileno())


def _fsync_dir(path: Path) -> None:
    # Directory fsync makes a rename durable on POSIX; Windows cannot open directories and does not need it.
    if os.name != "posix":
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _write_json_atomic(path: Path, data: dict, pause_before_replace: str | None = None) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as handle:
            json.dump(data, handle, indent=2, sort_keys=True)
            handle.write("\n")
            handle.flush()
            os.fsync(handle.fileno())
        if pause_before_replace:
            _pause_point(pause_before_replace)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    _fsync_dir(path.parent)


@dataclass(frozen=True)
class ModelVersion:
    """One complete version in a store."""

    name: str
    path: Path
    manifest: dict = field(default_factory=dict, compare=False)

    @property
    def model_path(self) -> Path:
        """The checkpoint file of this version."""
        return self.path / self.manifest.get("model", MODEL_NAME)

    @property
    def metadata(self) -> dict:
        """What the writer recorded about the run (source bags, steps, losses...)."""
        return self.manifest.get("metadata", {})


class ModelStore:
    """Versioned model directories under ``root`` with an atomic ``latest`` pointer.

    Args:
        root: the store directory; created when ``create`` is true.
        create: make ``root`` if it does not exist (writers); readers pass False.
    """

    def __init__(self, root: str | os.PathLike, create: bool = True) -> None:
        self.root = Path(root)
        if create:
            self.root.mkdir(parents=True, exist_ok=True)
        elif not self.root.is_dir():
            raise CheckpointError(f"{self.root}: model store does not exist")

    # ---- reading -------------------------------------------------------------------------------

    @property
    def pointer_path(self) -> Path:
        return self.root / POINTER_NAME

    def _read_manifest(self, version_dir: Path) -> dict:
        manifest_path = version_dir / MANIFEST_NAME
        try:
            manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        except FileNotFoundError as error:
            raise CheckpointError(f"{version_dir}: incomplete model version (no {MANIFEST_NAME})") from error
        except (OSError, ValueError) as error:
            raise CheckpointError(f"{manifest_path}: unreadable manifest: {error}") from error
        if not isinstance(manifest, dict) or not isinstance(manifest.get("files"), dict):
            raise CheckpointError(f"{manifest_path}: malformed manifest")
        model = manifest.get("model", MODEL_NAME)
        if not _plain_file_name(model):
            raise CheckpointError(f"{manifest_path}: model {str(model)[:80]!r} is not a file name in the version directory; refused")
        for name, entry in manifest["files"].items():
            if not _plain_relative_path(name) or not isinstance(entry, dict):
                raise CheckpointError(f"{manifest_path}: file entry {str(name)[:80]!r} leaves the version directory or is malformed; refused")
        if model not in manifest["files"]:
            raise CheckpointError(f"{manifest_path}: the model file {model!r} has no size and SHA-256 to check it against")
        return manifest

    def _check_inside(self, version_dir: Path) -> None:
        """Refuse a version directory that is a symlink or lies outside the store."""
        if version_dir.is_symlink() or not _inside(version_dir, self.root):
            raise CheckpointError(f"{version_dir}: model version is a symlink or lies outside the store {self.root}; refused")

    def versions(self) -> list[ModelVersion]:
        """Complete versions (those with a manifest), oldest first."""
        found = []
        for entry in self.root.iterdir() if self.root.is_dir() else []:
            match = _VERSION_RE.match(entry.name)
            if not match or not entry.is_dir() or entry.is_symlink():
                continue
            try:
                manifest = self._read_manifest(entry)
            except CheckpointError:
                continue
            found.append((int(match.group(1)), ModelVersion(entry.name, entry, manifest)))
        return [version for _, version in sorted(found, key=lambda item: item[0])]

    def latest(self) -> ModelVersion | None:
        """The version ``latest.json`` names, or None when nothing has been published yet.

        Raises:
            CheckpointError: the pointer exists but is unreadable or names a missing version.
        """
        try:
            text = self.pointer_path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        except OSError as error:
            raise CheckpointError(f"{self.pointer_path}: cannot read model pointer: {error}") from error
        try:
            pointer = json.loads(text)
            name = pointer["version"]
        except (ValueError, KeyError, TypeError) as error:
            raise CheckpointError(f"{self.pointer_path}: malformed model pointer") from error
        if not isinstance(name, str) or not _VERSION_RE.match(name):
            raise CheckpointError(f"{self.pointer_path}: pointer names an invalid version {name!r}")
        version_dir = self.root / name
        self._check_inside(version_dir)
        manifest = self._read_manifest(version_dir)
        version = ModelVersion(name, version_dir, manifest)
        if not version.model_path.is_file():
            raise CheckpointError(f"{version.model_path}: model file named by {self.pointer_path} is missing")
        recorded = manifest["files"][manifest.get("model", MODEL_NAME)].get("sha256")
        if pointer.get("sha256") not in (None, recorded) or pointer.get("model") not in (None, manifest.get("model", MODEL_NAME)):
            raise CheckpointError(f"{self.pointer_path}: pointer and the manifest of {name} disagree on the model; refused")
        return version

    def verify(self, version: ModelVersion) -> None:
        """Check every file of ``version`` against the sizes and SHA-256 in its manifest (and that none
        of them leaves the version directory, through a symlink or otherwise)."""
        for name, entry in version.manifest["files"].items():
            path = version.path / name
            if not _inside(path, version.path):
                raise CheckpointError(f"{path}: leaves model version {version.name} (a symlink out of it); refused")
            if not path.is_file():
                raise CheckpointError(f"{path}: missing from model version {version.name}")
            if path.stat().st_size != entry.get("size") or _sha256(path) != entry.get("sha256"):
                raise CheckpointError(f"{path}: does not match its manifest (corrupt or modified)")

    # ---- writing -------------------------------------------------------------------------------

    def clean_stale_staging(self) -> list[Path]:
        """Remove staging directories whose writer process is gone; return what was removed."""
        removed = []
        for entry in self.root.iterdir():
            if not entry.name.startswith(STAGING_PREFIX) or not entry.is_dir():
                continue
            pid_text = entry.name[len(STAGING_PREFIX):].split("-", 1)[0]
            # Our own pid may be another thread's staging in progress; a live pid is a writer at work.
            if pid_text.isdigit() and (int(pid_text) == os.getpid() or pid_alive(int(pid_text))):
                continue
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
        for entry in self.root.glob(f".{POINTER_NAME}.*.tmp"):
            pid_text = entry.name.split(".")[3]
            if pid_text.isdigit() and int(pid_text) != os.getpid() and not pid_alive(int(pid_text)):
                entry.unlink(missing_ok=True)
                removed.append(entry)
        return removed

    def prune(self, keep: int) -> list[Path]:
        """Delete all but the newest ``keep`` complete versions; never the one ``latest`` names."""
        if keep < 1:
            raise ValueError("keep must be at least 1")
        latest = self.latest()
        removed = []
        for version in self.versions()[:-keep]:
            if latest is not None and version.name == latest.name:
                continue
            # Rename first so a reader never sees a half-deleted version under its real name.
            doomed = self.root / f"{STAGING_PREFIX}0-{version.name}"
            os.rename(version.path, doomed)
            shutil.rmtree(doomed, ignore_errors=True)
            removed.append(version.path)
        return removed

    @contextlib.contextmanager
    def new_version(self, metadata: dict | None = None) -> Iterator[Path]:
        """Write a version: yields a staging directory; publishes it when the block ends cleanly.

        Write the checkpoint as ``<staging>/model.safetensors`` (plus any sidecar files). On an
        exception the staging directory is removed and ``latest`` is left as it was. The published
        version is available afterwards as ``store.last_published``.
        """
        self.clean_stale_staging()
        staging = self.root / f"{STAGING_PREFIX}{os.getpid()}-{uuid.uuid4().hex[:12]}"
        staging.mkdir()
        try:
            yield staging
            self.last_published = self._commit(staging, metadata or {})
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise

    def _commit(self, staging: Path, metadata: dict) -> ModelVersion:
        model_name = _model_file_name(staging)
        _pause_point("staging-written")
        files = {}
        for path in sorted(p for p in staging.rglob("*") if p.is_file()):
            _fsync_file(path)
            files[path.relative_to(staging).as_posix()] = {"size": path.stat().st_size, "sha256": _sha256(path)}
        manifest = {
            "format_version": FORMAT_VERSION,
            "model": model_name,
            "files": files,
            "created_unix": time.time(),
            "metadata": metadata,
        }
        _write_json_atomic(staging / MANIFEST_NAME, manifest)
        _pause_point("manifest-written")
        _fsync_dir(staging)
        final = self._rename_to_next_version(staging)
        _fsync_dir(self.root)
        _pause_point("version-renamed")
        pointer = {"version": final.name, "model": model_name, "sha256": files[model_name]["sha256"]}
        _write_json_atomic(self.pointer_path, pointer, pause_before_replace="pointer-tmp-written")
        log.info("published model %s", final)
        return ModelVersion(final.name, final, manifest)

    def _rename_to_next_version(self, staging: Path) -> Path:
        existing = [int(m.group(1)) for m in (_VERSION_RE.match(p.name) for p in self.root.iterdir()) if m]
        number = max(existing, default=0) + 1
        for _ in range(1000):
            final = self.root / f"v{number:04d}"
            try:
                # os.rename onto an existing non-empty directory fails: a concurrent writer keeps its name.
                if final.exists():
                    raise FileExistsError(final)
                os.rename(staging, final)
                return final
            except OSError:
                number += 1
        raise CheckpointError(f"{self.root}: could not allocate a version name")

    def publish_file(self, checkpoint_path: str | os.PathLike, metadata: dict | None = None) -> ModelVersion:
        """Copy an existing checkpoint (and its ``.json`` sidecar) into the store as a new version."""
        source = resolve_model_path(checkpoint_path)
        with self.new_version(metadata) as staging:
            # Names are kept: a checkpoint's sidecar records its weights file's name.
            shutil.copyfile(source, staging / source.name)
            sidecar = source.with_suffix(".json")
            if sidecar.is_file():
                shutil.copyfile(sidecar, staging / sidecar.name)
        return self.last_published


def _model_file_name(version_dir: Path) -> str:
    """``model.safetensors`` if present, else the directory's only ``.safetensors`` file."""
    if (version_dir / MODEL_NAME).is_file():
        return MODEL_NAME
    candidates = sorted(p.name for p in version_dir.glob("*.safetensors") if p.is_file())
    if len(candidates) != 1:
        raise CheckpointError(f"{version_dir}: nothing to publish (expected {MODEL_NAME} or one .safetensors file, found {candidates or 'none'})")
    return candidates[0]


def _inside(path: Path, directory: Path) -> bool:
    """True when ``path``, with every symlink resolved, lies inside ``directory`` (also resolved)."""
    try:
        path.resolve().relative_to(directory.resolve())
    except (ValueError, OSError, RuntimeError):  # RuntimeError: a symlink loop
        return False
    return True


def _plain_file_name(name: object) -> bool:
    return isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name


def _plain_relative_path(name: object) -> bool:
    return isinstance(name, str) and bool(name) and not name.startswith("/") and all(
        _plain_file_name(part) for part in name.split("/"))


def is_store(path: str | os.PathLike) -> bool:
    """True when ``path`` is a directory laid out as a model store."""
    path = Path(path)
    return path.is_dir() and ((path / POINTER_NAME).exists() or any(
        _VERSION_RE.match(p.name) or p.name.startswith(STAGING_PREFIX) for p in path.iterdir()))


def resolve_model_path(path: str | os.PathLike) -> Path:
    """Turn a model argument into the checkpoint file to load.

    Accepts a ``.safetensors`` file, a version directory (its manifest names the model file; or a
    directory holding ``model.safetensors``), or a store
    directory (follows ``latest.json``). Raises CheckpointError naming the path when none applies.

    A model reached through a store or a version directory is verified first: no path in it may leave
    the store (``../`` in a manifest, a version directory that is a symlink out of it), and every file
    must match the size and SHA-256 its manifest recorded.
    """
    path = Path(path)
    if path.is_file():
        return path
    if not path.exists():
        raise CheckpointError(f"{path}: model file or store does not exist")
    if path.is_dir():
        if (path / POINTER_NAME).exists():
            store = ModelStore(path, create=False)
            version = store.latest()
            assert version is not None
            store.verify(version)
            return version.model_path
        if (path / MANIFEST_NAME).is_file():  # a version directory
            store = ModelStore(path.parent, create=False)
            version = ModelVersion(path.name, path, store._read_manifest(path))
            if version.model_path.is_file():
                store.verify(version)
                return version.model_path
        if (path / MODEL_NAME).is_file():
            return path / MODEL_NAME
        if is_store(path):
            raise CheckpointError(f"{path}: model store has no published model yet (no {POINTER_NAME})")
        raise CheckpointError(f"{path}: directory holds neither {MODEL_NAME} nor a model store")
    raise CheckpointError(f"{path}: not a model file or directory")
