"""The ``nocal`` command: one subcommand per job, each a thin shell over the core.

Subcommands live in their own modules and are imported only when used, so ``nocal --help`` stays
fast and a missing optional dependency of one job does not break the others. Each module defines
``add_arguments(parser)`` and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

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


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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
    try:
        return int(args.run(args) or 0)
    except NocalError as error:
        print(f"nocal {args.command}: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"nocal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
