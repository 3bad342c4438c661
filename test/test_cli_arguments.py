"""Command lines a clumsy user types: every bad value is one line naming the option, before any work.

Also: errors are sorted deliberately by ``nocal_ros.cli.main`` (the user's: one line, exit 1; a bug:
traceback plus a request to report it, exit 70), and the core never imports from ``nocal_ros.commands``.
"""

from __future__ import annotations

import ast
import errno
from pathlib import Path

import pytest

from nocal_ros import cli
from nocal_ros.cli import main

# Exit codes (nocal_ros.cli): 1 the user's error, 2 a bad command line, 70 a bug.
EXIT_USER_ERROR, EXIT_USAGE, EXIT_BUG = 1, 2, 70

PACKAGE = Path(cli.__file__).resolve().parent

BAD_ARGUMENTS = [
    (["odometry", "BAG", "--out", "OUT", "--threads", "-1"], "--threads"),
    (["odometry", "BAG", "--out", "OUT", "--device", "bogus"], "--device"),
    (["odometry", "BAG", "--out", "OUT", "--frame-period", "nan"], "--frame-period"),
    (["odometry", "BAG", "--out", "OUT", "--frame-period", "0"], "--frame-period"),
    (["odometry", "BAG", "--out", "OUT", "--frame-period", "-0.1"], "--frame-period"),
    (["odometry", "BAG", "--out", "OUT", "--max-frames", "-1"], "--max-frames"),
    (["odometry", "BAG", "--out", "OUT", "--camera-height", "0"], "--camera-height"),
    (["odometry", "BAG", "--out", "OUT", "--camera-height", "nan"], "--camera-height"),
    (["odometry", "BAG", "--out", "OUT", "--base-to-camera", "0", "0", "0", "0", "0", "0", "nan"], "--base-to-camera"),
    (["odometry", "BAG", "--out", "OUT", "--ground-to-camera", "0", "0", "inf", "0", "0", "0", "1"], "--ground-to-camera"),
    (["synth", "--out", "OUT", "--fps", "nan"], "--fps"),
    (["synth", "--out", "OUT", "--speed", "inf"], "--speed"),
    (["synth", "--out", "OUT", "--frames", "0"], "--frames"),
    (["synth", "--out", "OUT", "--labelled-fraction", "1.5"], "--labelled-fraction"),
    (["synth", "--out", "OUT", "--seed", "-3"], "--seed"),
    (["synth", "--out", "OUT", "--threads", "-1"], "--threads"),
    (["train", "--config", "C", "--threads", "-1"], "--threads"),
    (["train", "--config", "C", "--device", "bogus"], "--device"),
    (["train", "--config", "C", "--steps", "0"], "--steps"),
    (["train", "--init", "--bag", "B", "--out", "S", "--keep", "-1"], "--keep"),
    (["train", "--init", "--bag", "B", "--out", "S", "--tolerance", "-1"], "--tolerance"),
    (["train", "--init", "--bag", "B", "--out", "S", "--tolerance", "nan"], "--tolerance"),
    (["train", "--init", "--bag", "B", "--out", "S", "--max-frames", "-1"], "--max-frames"),
    (["train", "--init", "--bag", "B", "--out", "S", "--hand-eye", *["1"] * 15, "inf"], "--hand-eye"),
    (["eval", "--bag", "B", "--batch-size", "0"], "--batch-size"),
    (["eval", "--bag", "B", "--max-frames", "-1"], "--max-frames"),
    (["eval", "--bag", "B", "--device", "bogus"], "--device"),
    (["demo", "--size", "4x4"], "--size"),
    (["bench", "--iterations", "0"], "--iterations"),
    (["bench", "--devices", "cpu,bogus"], "--devices"),
    (["bench", "--camera-height", "-1"], "--camera-height"),
]


@pytest.mark.parametrize("argv, option", BAD_ARGUMENTS, ids=[f"{a[0]} {o} {a[-1]}" for a, o in BAD_ARGUMENTS])
def test_bad_values_are_one_line_naming_the_option(argv, option, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == EXIT_USAGE
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"nocal {argv[0]}: error: argument {option}"), lines[0]
    assert "Traceback" not in captured.err and captured.out == ""


def test_the_trainer_nodes_settings_refuse_the_same_values(tmp_path):
    """The node builds a FinetuneConfig from its parameters (no argparse there): the same values are refused."""
    from nocal_ros.errors import ConfigError
    from nocal_ros.finetune import FinetuneConfig

    for bad in ({"keep_versions": -1}, {"threads": -1}, {"tolerance_s": -1.0}, {"tolerance_s": float("nan")},
                {"steps": 0}, {"T_tool_cam": [float("inf")] * 16}):
        with pytest.raises(ConfigError):
            FinetuneConfig(bags=["b.mcap"], output=str(tmp_path / "store"), **bad)


def test_good_values_still_parse():
    parser = cli.build_parser("odometry")
    args = parser.parse_args(["odometry", "BAG", "--out", "O", "--threads", "0", "--device", "cpu",
                              "--frame-period", "0.05", "--max-frames", "3", "--base-to-camera", *"0 0 0 0 0 0 1".split(),
                              "--camera-height", "1.65"])
    assert (args.threads, args.device, args.frame_period, args.max_frames, args.camera_height) == (0, "cpu", 0.05, 3, 1.65)
    args = cli.build_parser("synth").parse_args(["synth", "--out", "O", "--size", "32x24", "--speed", "0", "--fps", "30"])
    assert args.size == (32, 24) and args.speed == 0.0 and args.fps == 30.0


@pytest.mark.parametrize("content", [b"\x00\x01\x02\xff\xfe binary", b"a: [1, 2\n  b: }", b"[" * 100000, b"- just a list\n"])
def test_binary_or_malformed_config_is_one_line(tmp_path, capsys, content):
    config = tmp_path / "config.yaml"
    config.write_bytes(content)
    assert main(["train", "--config", str(config), "--out", str(tmp_path / "run")]) == EXIT_USER_ERROR
    captured = capsys.readouterr()
    assert len(captured.err.strip().splitlines()) == 1 and "Traceback" not in captured.err, captured.err
    assert str(config) in captured.err
    assert not (tmp_path / "run").exists()


def test_core_never_imports_the_command_layer():
    """``nocal_ros.commands`` sits on top of the core: only the CLI and the commands import it."""
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        relative = path.relative_to(PACKAGE)
        if relative.parts[0] == "commands" or relative.name == "cli.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            offenders += [f"{relative}:{node.lineno} imports {n}" for n in names if n.startswith("nocal_ros.commands")]
    assert not offenders, offenders


# ---- the user's errors and bugs ---------------------------------------------------------------------


def _synth_raising(monkeypatch, error: BaseException) -> None:
    import nocal_ros.commands.synth as synth

    def run(args):
        raise error

    monkeypatch.setattr(synth, "run", run)


def test_user_errors_are_one_line_and_exit_1(tmp_path, monkeypatch, capsys):
    from nocal_ros.errors import BagError

    cases = [
        BagError("in.mcap: cannot read the bag\n(corrupt: a multi-line\n   message from a library)"),
        OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "out.mcap")),
        PermissionError(errno.EACCES, "Permission denied", "/root/x"),
        MemoryError(),
    ]
    for error in cases:
        _synth_raising(monkeypatch, error)
        assert main(["synth", "--out", str(tmp_path / "x")]) == EXIT_USER_ERROR
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert err.startswith("nocal synth: error: ")


def test_enospc_names_the_file(tmp_path, monkeypatch, capsys):
    _synth_raising(monkeypatch, OSError(errno.ENOSPC, "No space left on device", "/data/out.mcap"))
    assert main(["synth", "--out", str(tmp_path / "x")]) == EXIT_USER_ERROR
    assert capsys.readouterr().err.strip() == "nocal synth: error: /data/out.mcap: No space left on device"


def test_a_missing_package_says_which_and_how_to_install_it(tmp_path, monkeypatch, capsys):
    _synth_raising(monkeypatch, ModuleNotFoundError("No module named 'torch'", name="torch"))
    assert main(["synth", "--out", str(tmp_path / "x")]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("nocal synth: error: the Python package 'torch' is not installed for ") and "pip install" in err


@pytest.mark.parametrize("error", [ZeroDivisionError("division by zero"), KeyError("stage"),
                                   ModuleNotFoundError("No module named 'nocal_ros.gone'", name="nocal_ros.gone"),
                                   OSError(errno.EBADF, "Bad file descriptor")])
def test_bugs_print_the_traceback_and_ask_for_a_report(tmp_path, monkeypatch, capsys, error):
    _synth_raising(monkeypatch, error)
    assert main(["synth", "--out", str(tmp_path / "x")]) == EXIT_BUG
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and type(error).__name__ in err
    assert err.strip().splitlines()[-1].startswith("nocal synth: internal error: this is a bug in nocal")
