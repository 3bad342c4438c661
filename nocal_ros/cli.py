"""The ``nocal`` command: one subcommand per job, each a thin shell over the core.

Subcommands live in their own modules and are imported only when used, so ``nocal --help`` stays
fast and a missing optional dependency of one job does not break the others. Each module defines
``add_arguments(parser)`` and ``run(args) -> int``.

Errors are sorted deliberately (see :func:`main`):

* the user's, one line on stderr and exit 1: a :class:`~nocal_ros.errors.NocalError` (bad input, named
  file and problem), an operating-system error about a file or the machine (disk full, permission
  denied, no such file, read-only filesystem, too many open files, I/O error), and running out of memory;
* a bad command line: argparse's one line and exit 2;
* Ctrl-C: exit 130;
* anything else is a bug in nocal: the traceback, then one line asking for a report, and exit 70
  (``EX_SOFTWARE``).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import sys
import traceback

from nocal_ros.errors import NocalError

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("nocal_ros.commands.demo", "render a short bag from an unseen camera and run odometry on it"),
    "synth": ("nocal_ros.commands.synth", "render a synthetic rosbag2 dataset with ground truth"),
    "train": ("nocal_ros.commands.train", "pretrain a NOCaL model, or fine-tune one on bags into a model store (--init)"),
    "eval": ("nocal_ros.commands.eval", "evaluate a model's calibration and odometry against a bag's ground truth"),
    "odometry": ("nocal_ros.commands.odometry", "replay a bag offline: odometry bag, trajectory, calibration, report"),
    "bench": ("nocal_ros.commands.bench", "measure pose-head and estimator latency"),
    "import": ("nocal_ros.commands.import_data", "convert KITTI, EuRoC, TUM RGB-D, VAMR, an image folder or a video to a rosbag2"),
}


#: OSErrors that describe the user's files or machine rather than a fault in nocal.
USER_ERRNOS = frozenset(
    getattr(errno, name) for name in (
        "ENOSPC", "EDQUOT", "EACCES", "EPERM", "EROFS", "ENOENT", "ENOTDIR", "EISDIR", "EEXIST", "ENOTEMPTY",
        "ENAMETOOLONG", "EMFILE", "ENFILE", "EIO", "ELOOP", "EFBIG", "ETXTBSY", "EBUSY",
    ) if hasattr(errno, name)
)
EXIT_USER_ERROR = 1
EXIT_USAGE = 2
EXIT_BUG = 70  # sysexits.h EX_SOFTWARE
EXIT_INTERRUPTED = 130
BUG_HINT = ("this is a bug in nocal, not a problem with your input: please report it with the traceback above "
            "and the command line (nocal_ros issue tracker)")


class _Parser(argparse.ArgumentParser):
    """argparse with its error on one line (the usage block stays behind ``--help``)."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def one_line(text: object) -> str:
    """``text`` with every run of whitespace (newlines included) as one space."""
    return " ".join(str(text).split())


def os_error_message(error: OSError) -> str:
    """``file: reason`` for an OSError, as the user needs it."""
    names = [str(n) for n in (error.filename, error.filename2) if n is not None]
    reason = error.strerror or str(error)
    return one_line(f"{' -> '.join(names)}: {reason}" if names else reason)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="nocal",
        description="NOCaL: odometry and calibration from an uncalibrated camera.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(sub)
            sub.set_defaults(run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if a in SUBCOMMANDS), None)
    parser = build_parser(command)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="[%(levelname)s] %(name)s: %(message)s",
    )
    if not getattr(args, "run", None):
        parser.print_help()
        return 2
    prefix = f"nocal {args.command}"
    try:
        return int(args.run(args) or 0)
    except NocalError as error:
        print(f"{prefix}: error: {one_line(error)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{prefix}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError:
        print(f"{prefix}: error: out of memory (try a smaller --max-frames, batch or image size)", file=sys.stderr)
        return EXIT_USER_ERROR
    except ModuleNotFoundError as error:
        if not error.name or error.name.split(".")[0] == "nocal_ros":
            return _report_bug(prefix)  # a module of our own missing is a broken install or a bug
        # Another package missing is the environment's: a replay run by a Python without the requirements.
        print(f"{prefix}: error: the Python package '{error.name}' is not installed for {sys.executable} "
              f"(install the requirements: pip install -r requirements.txt -e .)", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as error:
        if error.errno not in USER_ERRNOS:
            return _report_bug(prefix)
        print(f"{prefix}: error: {os_error_message(error)}", file=sys.stderr)
        return EXIT_USER_ERROR
    except Exception as error:  # noqa: BLE001 - the one place that turns an unexpected exception into a bug report
        if type(error).__name__ == "OutOfMemoryError":  # torch.cuda.OutOfMemoryError, without importing torch here
            print(f"{prefix}: error: out of GPU memory ({one_line(error)[:200]})", file=sys.stderr)
            return EXIT_USER_ERROR
        return _report_bug(prefix)


def _report_bug(prefix: str) -> int:
    traceback.print_exc()
    print(f"{prefix}: internal error: {BUG_HINT}", file=sys.stderr)
    return EXIT_BUG


if __name__ == "__main__":
    sys.exit(main())
