"""The geonav command: help is cheap, errors are one line and a non-zero exit."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import rasterio
from rasterio.transform import from_origin

from geonav.cli import main


def test_help_lists_every_command(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for cmd in ("tiles", "tasks", "train", "eval", "meta-train", "curriculum", "experiment",
                "fly", "demo"):
        assert cmd in out, cmd


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
