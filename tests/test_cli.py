"""The geonav command: help is cheap, errors are one line and a non-zero exit."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import rasterio
from rasterio.transform import from_origin

from geonav.cli import main


def test_help_lists_every_command(capsys):
    # no command is a usage error (exit 2, help on stderr), as a missing argument
    assert main([]) == 2
    err = capsys.readouterr().err
    for cmd in ("tiles", "tasks", "train", "eval", "meta-train", "curriculum", "experiment",
                "fly", "demo"):
        assert cmd in err, cmd
    assert err.strip().endswith("geonav: error: give a command (see above)")
    for group in ("tiles", "tasks", "experiment", "mavlink"):
        assert main([group]) == 2, group
        assert f"geonav {group}: error: give a command" in capsys.readouterr().err


def test_verbose_and_quiet_anywhere_on_every_command(capsys):
    """-v/-q come from one parent parser shared by every subcommand, at any depth, before
    or after it (issue 34: -v worked only before the subcommand; there was no -q)."""
    import argparse

    from geonav.cli import build_parser
    from geonav.cliutil import apply_verbosity

    parser = build_parser()
    train = ["train", "--scene", "s", "--tasks", "t", "--out", "o"]
    for argv, verbose, quiet in ((train, 0, False), (["-v", *train], 1, False),
                                 ([*train, "-v"], 1, False), ([*train, "-vv"], 2, False),
                                 (["-vv", *train], 2, False), ([*train, "-q"], 0, True),
                                 (["-q", "experiment", "report", "c.toml"], 0, True),
                                 (["experiment", "report", "c.toml", "-v"], 1, False),
                                 (["tiles", "info", "--verbose", "x"], 1, False),
                                 (["mavlink", "emulate", "-q"], 0, True)):
        args = parser.parse_args(argv)
        assert (args.verbose, args.quiet) == (verbose, quiet), argv
    assert apply_verbosity(parser.parse_args([*train, "-q"])) == 40  # logging.ERROR
    assert apply_verbosity(parser.parse_args([*train, "-v"])) == 20  # logging.INFO
    assert apply_verbosity(argparse.Namespace()) == 30  # a parser without them: WARNING
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)][0]
    for name, sub in subs.choices.items():
        flags = {o for a in sub._actions for o in a.option_strings}
        assert {"-v", "--verbose", "-q", "--quiet"} <= flags, name
    for extra in ([], ["--param", "a.b=1"]):  # experiment run had no --no-progress
        cmd = "sweep" if extra else "run"
        args = parser.parse_args(["experiment", cmd, "c.toml", *extra, "--no-progress"])
        assert args.no_progress, cmd
    try:
        parser.parse_args([*train, "-v", "-q"])
    except SystemExit as err:
        assert err.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_help_does_not_import_heavy_modules():
    code = ("import sys, geonav.cli as c; c.build_parser(); "
            "print(sorted(m for m in ('torch', 'rasterio', 'pymavlink', 'mavsdk', 'matplotlib')"
            " if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_bad_input_is_one_line_and_exit_2(tmp_path):
    path = tmp_path / "nocrs.tif"
    with rasterio.open(path, "w", driver="GTiff", width=20, height=20, count=3, dtype="uint8",
                       transform=from_origin(0, 20, 1, 1)) as dst:
        dst.write(np.zeros((3, 20, 20), np.uint8))
    run = subprocess.run([sys.executable, "-m", "geonav.cli", "tiles", "ingest", str(path),
                          "--name", "X", "--out", str(tmp_path / "x")],
                         capture_output=True, text=True)
    assert run.returncode == 2
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert lines == [f"geonav: error: {path} has no CRS; assign one first, e.g. "
                     f"'gdal_edit.py -a_srs EPSG:xxxx nocrs.tif'"]
    assert not (tmp_path / "x").exists()


def test_missing_scene_and_tasks_errors(tmp_path, capsys):
    assert main(["tasks", "make", str(tmp_path / "nope"), "-o", str(tmp_path / "t.json")]) == 2
    assert "does not exist or is not a folder" in capsys.readouterr().err


def test_parser_errors_are_one_line_and_negative_values_parse(capsys):
    import pytest

    with pytest.raises(SystemExit) as info:
        main(["tiles", "ingest", "x", "--name", "A", "--out", "o", "--bbox", "-1,2"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--bbox" in err and "west,south,east,north" in err
    # a western-hemisphere bbox is a value, not an option: the error is about the file
    assert main(["tiles", "ingest", "missing.tif", "--name", "A", "--out", "o",
                 "--bbox", "-122.45,37.75,-122.40,37.80"]) == 2
    assert "missing.tif does not exist" in capsys.readouterr().err


def test_nothing_imports_the_root_cli():
    import ast
    from pathlib import Path

    import geonav

    root = Path(geonav.__file__).parent
    for path in root.rglob("*.py"):
        if path.name == "cli.py" and path.parent == root:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert node.module != "geonav.cli", path


def test_long_steps_write_progress_lines_in_a_log(monkeypatch, capsys):
    """Not on a terminal, progress is a line every ~30 s (GEONAV_PROGRESS_S), also through
    a phase that blocks in one long call (the chance figures of a task set: `tasks make`
    ran 14.6 min without a line); none once the phase is done, none with -q."""
    import time

    from geonav import cliutil

    monkeypatch.setenv("GEONAV_PROGRESS_S", "0.1")
    monkeypatch.setattr(cliutil, "is_terminal", lambda: False)
    progress = cliutil.progress_bar("tasks")
    progress("chance figures", 0.0)
    time.sleep(0.5)  # one long call, no progress calls
    progress("chance figures", 1.0)
    time.sleep(0.3)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) >= 2 and all(ln.startswith("tasks: chance figures 0% (") for ln in lines)
    assert "\r" not in "".join(lines)
    progress.close()
    assert cliutil.progress_bar("x", disable=True)("p", 0.5) is None
    monkeypatch.setattr(cliutil, "QUIET", True)
    quiet = cliutil.progress_bar("x")
    quiet("p", 0.0)
    time.sleep(0.3)
    assert capsys.readouterr().err == ""


def test_task_samplers_report_progress(scene):
    from geonav.tasks import sample_meta_tasks, whole_scene_tasks

    seen: list[tuple[str, float]] = []
    whole_scene_tasks(scene, (75.0, 45.0), progress=lambda p, f: seen.append((p, f)))
    assert ("obstacles", 1.0) in seen and seen[-1] == ("target", 1.0)
    seen.clear()
    sample_meta_tasks(scene, 2, size_m=60.0, alt_m=30.0, progress=lambda p, f: seen.append((p, f)))
    assert seen == [("meta-tasks", 0.0), ("meta-tasks", 0.5), ("meta-tasks", 1.0)]


def test_package_docstrings_name_the_entry_points():
    """help(geonav) and help(geonav.policy) name the default engine's entry point, PPO and
    the checkpoint evaluation, and each one they name is importable from geonav.policy."""
    import geonav
    import geonav.policy as policy

    for doc in (geonav.__doc__, policy.__doc__):
        for name in ("build_trainer", "PPO", "evaluate_checkpoint", "build_meta_trainer",
                     "run_curriculum"):
            assert name in doc, name
    assert callable(policy.build_trainer) and callable(policy.evaluate_checkpoint)
    assert policy.PPOConfig.__name__ == "PPOConfig"
    code = ("import sys, geonav.policy; print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "False"  # the package itself stays cheap to import
