"""camera_info_manager's calibration URLs, without ROS: where a camera's calibration YAML lives.

The rules are camera_info_manager's (ros-perception/image_common, ``camera_info_manager.cpp``), so a
robot's existing calibration files and launch arguments work unchanged:

* ``file:///abs/path.yaml``: that file (the scheme is case-insensitive);
* ``package://pkg/rel/path.yaml``: ``rel/path.yaml`` in the package's share directory (ament index);
* ``""``: the default, :data:`DEFAULT_URL` = ``file://${ROS_HOME}/camera_info/${NAME}.yaml``;
* ``${NAME}`` becomes the camera name, ``${ROS_HOME}`` the ``ROS_HOME`` environment variable or else
  ``$HOME/.ros``.

Where camera_info_manager logs and carries on, this module raises :class:`~nocal_ros.errors.ConfigError`
(an unknown ``${...}`` variable, ``flash:///``, a bare path): a node started with a URL it cannot use
says so in one line. A URL whose file does not exist yet is not an error: it is where the calibration
will be saved. The files are ROS camera_calibration YAML, read and written by
:class:`nocal_ros.lens.CameraCalibration` (the one YAML reader and writer).
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path

from nocal_ros.errors import ConfigError
from nocal_ros.lens import CameraCalibration

DEFAULT_URL = "file://${ROS_HOME}/camera_info/${NAME}.yaml"
_VARIABLE = re.compile(r"\$\{([^}]*)\}")
_CAMERA_NAME = re.compile(r"^[A-Za-z0-9_]+$")

PackageShare = Callable[[str], str]


def check_camera_name(name: str) -> str:
    """``name`` if camera_info_manager accepts it (letters, digits, ``_``), else ConfigError."""
    if not isinstance(name, str) or not _CAMERA_NAME.match(name):
        raise ConfigError(f"camera name {name!r} is not valid: camera_info_manager allows only letters, digits and '_'")
    return name


def ros_home(environ: Mapping[str, str] | None = None) -> str:
    """``$ROS_HOME``, else ``$HOME/.ros`` (what ROS 2 logs and camera_info_manager use)."""
    environ = os.environ if environ is None else environ
    if environ.get("ROS_HOME"):
        return environ["ROS_HOME"]
    home = environ.get("HOME") or str(Path.home())
    return str(Path(home) / ".ros")


def resolve_url(url: str, camera_name: str, environ: Mapping[str, str] | None = None) -> str:
    """``url`` (``""`` means :data:`DEFAULT_URL`) with ``${NAME}`` and ``${ROS_HOME}`` substituted."""
    check_camera_name(camera_name)

    def substitute(match: re.Match) -> str:
        variable = match.group(1)
        if variable == "NAME":
            return camera_name
        if variable == "ROS_HOME":
            return ros_home(environ)
        raise ConfigError(f"camera_info_url {url!r}: unknown variable ${{{variable}}} (known: ${{NAME}}, ${{ROS_HOME}})")

    return _VARIABLE.sub(substitute, url or DEFAULT_URL)


def _ament_package_share(package: str) -> str:
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:
        raise ConfigError(f"package://{package}/... URLs need ROS (ament_index_python) to find the package") from None
    try:
        return get_package_share_directory(package)
    except PackageNotFoundError:
        raise ConfigError(f"package {package!r} of a package:// calibration URL is not installed (ament index)") from None


def url_path(url: str, camera_name: str, *, package_share: PackageShare | None = None,
             environ: Mapping[str, str] | None = None) -> Path:
    """The calibration file a camera_info_manager URL names (it need not exist yet).

    Args:
        url: ``file:///...``, ``package://pkg/...`` or ``""`` (the default URL).
        camera_name: substituted for ``${NAME}``.
        package_share: package name -> share directory (default: the ament index).
        environ: for ``${ROS_HOME}`` (default: ``os.environ``).
    """
    resolved = resolve_url(url, camera_name, environ)
    scheme = resolved[:10].lower()
    if scheme.startswith("file:///"):
        return Path(resolved[len("file://"):])
    if scheme == "package://":
        package, _, relative = resolved[len("package://"):].partition("/")
        if not package or not relative:
            raise ConfigError(f"camera_info_url {url!r}: a package URL is package://PACKAGE/PATH")
        return Path((package_share or _ament_package_share)(package)) / relative
    raise ConfigError(f"camera_info_url {url!r}: not a file:/// or package:// URL (camera_info_manager's conventions)")


def load_calibration(url: str, camera_name: str, **kwargs) -> tuple[CameraCalibration | None, Path]:
    """``(calibration, path)``: the YAML at ``url``, or None when no file is there yet.

    A file that exists but is not a valid camera_calibration YAML raises ConfigError naming it.
    """
    path = url_path(url, camera_name, **kwargs)
    if not path.is_file():
        return None, path
    return CameraCalibration.load(path), path


def save_calibration(calibration: CameraCalibration, url: str, camera_name: str, **kwargs) -> Path:
    """Write ``calibration`` as camera_calibration YAML where ``url`` points (directories made as
    camera_info_manager does), under ``camera_name``; returns the path. The write is atomic."""
    path = url_path(url, camera_name, **kwargs)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        dataclasses.replace(calibration, camera_name=camera_name).save(path)
    except OSError as error:
        raise ConfigError(f"{path}: cannot write the calibration ({error.strerror or error})") from None
    return path
