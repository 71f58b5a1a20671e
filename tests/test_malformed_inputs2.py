"""Malformed and hostile inputs, round 2 (issue 33).

Nothing of the user's is ever destroyed (``--force`` replaces only geonav's own output
of that kind; a second writer of the same output is refused; flight records are never
overwritten), checkpoints that cannot fly are refused, every expected failure is one
line, numbers are bounded where they enter, and a scene package is cross-checked on
open. Each case failed on the code before this round.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from geonav.cli import main
from geonav.errors import GeonavWarning, OutputBusy

rasterio = pytest.importorskip("rasterio")

from raster_helpers import UTM31, X0, Y0, make_utm_tif, texture, write_raster  # noqa: E402

_write = write_raster
_texture = texture


@pytest.fixture(scope="module")
def utm_tif(tmp_path_factory) -> Path:
    return make_utm_tif(tmp_path_factory)


def _cli(argv: list, capsys) -> tuple[int, str, str]:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GeonavWarning)
            rc = main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse refuses a value: exit 2 after one line
        rc = exit_.code
    out, err = capsys.readouterr()
    return rc, out, err


def _one_line_error(rc: int, err: str, needle: str = "") -> None:
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("warning: ")]
    assert rc == 2, err
    assert len(lines) == 1 and "error" in lines[0], err
    assert "Traceback" not in err
    assert needle in lines[0], err


def _ingest_argv(src: Path, out: Path, *extra) -> list:
    return ["tiles", "ingest", src, "--name", "A", "--out", out, "--compress", "DEFLATE", *extra]


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


# -- 1. nothing of the user's is destroyed --------------------------------------------------

def test_force_refuses_a_folder_that_is_not_a_scene_package(tmp_path, capsys, utm_tif):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("three years of work")
    (mine / "data").mkdir()
    (mine / "data" / "x.csv").write_text("1,2,3")
    before = _tree(mine)
    rc, _, err = _cli(_ingest_argv(utm_tif, mine, "--force"), capsys)
    _one_line_error(rc, err, "not a scene package")
    assert "choose another output path" in err
    assert _tree(mine) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]  # no temp, no lock left


def test_force_out_dot_never_wipes_the_working_folder(tmp_path, capsys, utm_tif, monkeypatch):
    (tmp_path / "notes.txt").write_text("keep me")
    monkeypatch.chdir(tmp_path)
    rc, _, err = _cli(_ingest_argv(utm_tif, ".", "--force"), capsys)
    _one_line_error(rc, err, "refusing to replace")
    assert (tmp_path / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_force_refuses_a_scene_package_holding_the_users_files(tmp_path, capsys, utm_tif):
    out = tmp_path / "S"
    rc, _, err = _cli(_ingest_argv(utm_tif, out), capsys)
    assert rc == 0, err
    (out / "my_notes.md").write_text("field notes")
    rc, _, err = _cli(_ingest_argv(utm_tif, out, "--force"), capsys)
    _one_line_error(rc, err, "files geonav did not write (my_notes.md)")
    assert (out / "my_notes.md").read_text() == "field notes"
    (out / "my_notes.md").unlink()
    rc, _, err = _cli(_ingest_argv(utm_tif, out, "--force"), capsys)  # its own: replaced
    assert rc == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["S"]


_HOLD_LOCK = """
import sys, time
from geonav.outputs import output_lock
with output_lock(sys.argv[1]):
    print("locked", flush=True)
    sys.stdin.readline()
"""


def _holding_lock(target: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", _HOLD_LOCK, str(target)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_ingest_into_the_same_out_is_refused_at_once(tmp_path, capsys, utm_tif):
    out = tmp_path / "S"
    proc = _holding_lock(out)  # another geonav, minutes into its ingest
    try:
        rc, _, err = _cli(_ingest_argv(utm_tif, out), capsys)
        _one_line_error(rc, err, f"pid {proc.pid}")
        assert "being written by another geonav" in err and not out.exists()
        rc, _, err = _cli(_ingest_argv(utm_tif, out, "--force"), capsys)
        _one_line_error(rc, err, "being written by another geonav")
    finally:
        proc.communicate("\n", timeout=30)
    rc, _, err = _cli(_ingest_argv(utm_tif, out), capsys)  # the first is done: free again
    assert rc == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["S"]


def test_lock_of_a_killed_writer_is_free(tmp_path):
    from geonav.outputs import lock_path, output_lock

    proc = _holding_lock(tmp_path / "S")
    proc.kill()
    proc.wait(30)
    assert lock_path(tmp_path / "S").exists()  # left behind by SIGKILL
    with output_lock(tmp_path / "S"):
        with output_lock(tmp_path / "S"):  # re-entrant in one process
            pass
    assert list(tmp_path.iterdir()) == []


def test_lock_busy_is_an_output_error(tmp_path):
    from geonav.outputs import output_lock

    proc = _holding_lock(tmp_path / "x.json")
    try:
        with pytest.raises(OutputBusy, match="choose another -o path"):
            with output_lock(tmp_path / "x.json", "-o"):
                pass
    finally:
        proc.communicate("\n", timeout=30)


def test_flight_records_are_never_overwritten(tmp_path):
    from geonav.mavlink_bridge.record import FlightRecorder

    first = FlightRecorder(tmp_path / "flight")
    first.write("header", n=1)
    first.close()
    record = (tmp_path / "flight" / "flight.jsonl").read_bytes()
    second = FlightRecorder(tmp_path / "flight")
    second.write("header", n=2)
    second.close()
    assert second.out_dir == tmp_path / "flight-2"
    assert (tmp_path / "flight" / "flight.jsonl").read_bytes() == record
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "track.png").write_bytes(b"my picture")
    third = FlightRecorder(tmp_path / "mine")
    third.close()
    assert third.out_dir == tmp_path / "mine-2"
    assert (tmp_path / "mine" / "track.png").read_bytes() == b"my picture"


@pytest.fixture(scope="module")
def package(tmp_path_factory, utm_tif) -> Path:
    from geonav.tiles.ingest import ingest

    d = tmp_path_factory.mktemp("pkg")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeonavWarning)
        ingest([utm_tif], name="P", out=d / "P", compress="DEFLATE")
    return d / "P"


def _make_tasks(package: Path, out: Path, *extra) -> list:
    return ["tasks", "make", package, "--kind", "scene", "--alts", "15", "--step", "10",
            "--max-blind", "none", "-o", out, *extra]


def test_tasks_make_never_replaces_a_file_it_did_not_write(tmp_path, capsys, package):
    theirs = tmp_path / "tasks.json"
    theirs.write_text('{"my": "data"}')
    rc, _, err = _cli(_make_tasks(package, theirs), capsys)
    _one_line_error(rc, err, "pass --force")
    rc, _, err = _cli(_make_tasks(package, theirs, "--force"), capsys)
    _one_line_error(rc, err, "not a geonav task file")
    assert theirs.read_text() == '{"my": "data"}'
    ours = tmp_path / "ours.json"
    rc, _, err = _cli(_make_tasks(package, ours), capsys)
    assert rc == 0, err
    rc, _, err = _cli(_make_tasks(package, ours), capsys)
    _one_line_error(rc, err, "exists; pass --force")
    rc, _, err = _cli(_make_tasks(package, ours, "--force", "--seed", "3"), capsys)
    assert rc == 0, err
    assert json.loads(ours.read_text())["tasks"]


def test_training_refuses_a_folder_of_the_users_files(tmp_path):
    from geonav.errors import ConfigError
    from geonav.policy.a3c import train_a3c
    from geonav.policy.config import A3CConfig
    from geonav.policy.testing import tiny_env_factory, tiny_net

    (tmp_path / "config.json").write_text('{"my": "settings"}')
    with pytest.raises(ConfigError, match="holds config.json, which geonav did not write"):
        train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=2, workers=0),
                  out_dir=tmp_path)
    assert (tmp_path / "config.json").read_text() == '{"my": "settings"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json"]


def test_two_trainings_into_one_out_do_not_mix(tmp_path):
    from geonav.policy.a3c import train_a3c
    from geonav.policy.config import A3CConfig
    from geonav.policy.testing import tiny_env_factory, tiny_net

    run = tmp_path / "run"
    proc = _holding_lock(run)  # another training into the same folder
    try:
        with pytest.raises(OutputBusy, match="being written by another geonav"):
            train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=2, workers=0),
                      out_dir=run)
    finally:
        proc.communicate("\n", timeout=30)
    assert not (run / "metrics.csv").exists() and not (run / "config.json").exists()
    train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=2, workers=0), out_dir=run)
    assert (run / "checkpoints" / "final.pt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # lock released


def test_preview_replaces_only_its_own_picture(tmp_path, capsys, package):
    theirs = tmp_path / "photo.png"
    theirs.write_bytes(b"\x89PNG\r\n\x1a\n holiday")
    rc, _, err = _cli(["tiles", "preview", package, "-o", theirs, "--force"], capsys)
    _one_line_error(rc, err, "not a picture geonav drew")
    assert theirs.read_bytes() == b"\x89PNG\r\n\x1a\n holiday"
    ours = tmp_path / "p.png"
    assert _cli(["tiles", "preview", package, "-o", ours, "--max-px", "200"], capsys)[0] == 0
    rc, _, err = _cli(["tiles", "preview", package, "-o", ours], capsys)
    _one_line_error(rc, err, "exists; pass --force")
    assert _cli(["tiles", "preview", package, "-o", ours, "--max-px", "200", "--force"],
                capsys)[0] == 0
    rc, _, err = _cli(["tiles", "preview", package, "-o", tmp_path / "p.xyz"], capsys)
    _one_line_error(rc, err, "cannot draw a '.xyz' picture")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png", "photo.png"]


# -- 4. checkpoints that cannot fly are refused ---------------------------------------------

@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    from geonav.policy.a3c import train_a3c
    from geonav.policy.config import A3CConfig
    from geonav.policy.testing import tiny_env_factory, tiny_net

    run = tmp_path_factory.mktemp("run") / "r"
    train_a3c(tiny_env_factory(), tiny_net(), A3CConfig(episodes=2, workers=0), out_dir=run)
    return run / "checkpoints" / "final.pt"


def _altered(checkpoint: Path, tmp_path: Path, edit) -> Path:
    import torch

    blob = torch.load(checkpoint, weights_only=True)
    edit(blob)
    path = tmp_path / "altered.pt"
    torch.save(blob, path)
    return path


def _nan_weights(blob):
    for v in blob["model"].values():
        if v.is_floating_point():
            v.fill_(float("nan"))


@pytest.mark.parametrize("edit,message", [
    (_nan_weights, "non-finite weights"),
    (lambda b: b["model"]["actor.weight"].__setitem__((0, 0), float("inf")),
     "non-finite weights.*'actor.weight'"),
    (lambda b: b["meta"]["net"].update(hidden_size=b["meta"]["net"]["hidden_size"] * 2),
     "do not fit its architecture record"),
    (lambda b: b["meta"].update(obs_size_px=b["meta"]["obs_size_px"] * 2),
     "obs_size_px=64 in its meta but its network has obs_size_px=32"),
    (lambda b: b["model"].pop("actor.bias"), r"missing \['actor.bias'\]"),
])
def test_a_checkpoint_that_cannot_act_is_refused_on_load(checkpoint, tmp_path, edit, message):
    from geonav.errors import CheckpointError
    from geonav.policy.checkpoint import load_checkpoint

    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(_altered(checkpoint, tmp_path, edit))


def test_a_nan_checkpoint_is_neither_flown_nor_evaluated(checkpoint, tmp_path, capsys):
    from geonav.testing import textured_scene

    bad = _altered(checkpoint, tmp_path, _nan_weights)
    scene = textured_scene(60.0, 0.5, towers=False)
    scene.save(tmp_path / "S")
    rc, _, err = _cli(["fly", bad, "--scene", tmp_path / "S", "--dry-run", "--target", "2,2",
                       "--alt", "10", "--out", tmp_path / "flight"], capsys)
    _one_line_error(rc, err, "non-finite weights")
    assert not (tmp_path / "flight").exists()  # refused before anything flew or was written
    rc, _, err = _cli(["eval", bad, "--scene", tmp_path / "S", "--tasks", tmp_path / "t.json"],
                      capsys)
    _one_line_error(rc, err, "non-finite weights")


def test_pickled_code_in_a_checkpoint_is_refused_without_torchs_advice(tmp_path):
    import torch

    from geonav.errors import CheckpointError
    from geonav.policy.checkpoint import load_checkpoint

    class Payload:
        def __reduce__(self):
            return (print, ("this would run",))

    torch.save({"format": "geonav-policy", "x": Payload()}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="holds more than weights") as info:
        load_checkpoint(tmp_path / "evil.pt")
    assert "weights_only" not in str(info.value) and "callable 'print'" in str(info.value)
    assert "safe_globals" not in str(info.value)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt or truncated") as info:
        load_checkpoint(tmp_path / "junk.pt")
    assert "weights_only" not in str(info.value)


def test_outputs_that_are_not_finite_are_refused_before_arming(checkpoint, tmp_path):
    import torch

    from geonav.errors import CheckpointError
    from geonav.mavlink_bridge.backends import open_vehicle
    from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig
    from geonav.mavlink_bridge.flight import FlightConfig, run_flight
    from geonav.policy.inference import PolicyRunner
    from geonav.tasks import Lattice
    from geonav.testing import textured_scene

    def huge(blob):  # finite, but every sum overflows
        for v in blob["model"].values():
            if v.is_floating_point():
                v.fill_(3e38)

    big = _altered(checkpoint, tmp_path, huge)
    policy = PolicyRunner.from_checkpoint(big)  # finite weights, infinite logits
    view = np.full((32, 32, 3), 128, np.uint8)
    with pytest.raises(CheckpointError, match="outputs are not finite"):
        policy.check_outputs(view, view)
    assert all(torch.isfinite(p).all() for p in policy.agent.model.parameters())
    scene = textured_scene(60.0, 0.5, towers=False)
    policy.meta.update(alt_m=10.0, step_m=5.0)
    home = scene.frame.to_lonlat(Lattice(scene.bounds_m, 5.0).center((5, 5)), 0.0)
    with Emulator(EmulatorConfig(home=home, time_scale=6.0, boot_s=1.0, origin_s=0.6,
                                 local_position_s=1.2)) as emu:
        result = run_flight(open_vehicle(emu.connect_url, "pymavlink"), scene, policy,
                            FlightConfig(target_cell=(7, 6), start_cell=(5, 5)), tmp_path / "f")
        assert result.outcome == "refused" and "outputs are not finite" in result.reason
        assert not emu.armed and not emu.setpoints


# -- 2. one line for every expected failure ------------------------------------------------

def _entry_points() -> list[tuple[str, ...]]:
    """Every subcommand path of ``geonav`` that has a handler."""
    import argparse

    from geonav.cli import build_parser

    found = []

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, (*path, name))
        if path and parser.get_default("handler") is not None:
            found.append(path)

    walk(build_parser(), ())
    return found


def _gdal_error():
    from rasterio._err import CPLE_FileIOError

    return CPLE_FileIOError(3, 3, "out/.S.geonav-tmp/ortho.tif: No space left on device")


FAILURES = {
    "gdal": (_gdal_error, "GDAL could not read or write a raster"),
    "memory": (MemoryError, "out of memory"),
    "overflow": (lambda: OverflowError("Python int too large to convert to C long"),
                 "a number is out of range"),
    "unicode": (lambda: b"\xff".decode("utf-8"), "is not UTF-8 text"),
    "disk full": (lambda: OSError(28, "No space left on device", "out/x"),
                  "cannot write out/x: No space left on device"),
}


@pytest.mark.parametrize("kind", sorted(FAILURES))
def test_every_entry_point_turns_each_failure_class_into_one_line(monkeypatch, capsys, kind):
    import argparse

    from geonav.cli import GeonavParser

    make, needle = FAILURES[kind]
    entries = _entry_points()
    assert {("tiles", "ingest"), ("tasks", "make"), ("train",), ("eval",), ("fly",)} <= \
        set(entries)

    def fail(args):
        raise make()  # (the unicode case raises inside make())

    for path in entries:
        monkeypatch.setattr(GeonavParser, "parse_args", lambda self, argv=None, ns=None:
                            argparse.Namespace(verbose=0, handler=fail))
        rc, _, err = _cli(list(path), capsys)
        _one_line_error(rc, err, needle)
    monkeypatch.setattr(GeonavParser, "parse_args", lambda self, argv=None, ns=None:
                        argparse.Namespace(verbose=1, handler=fail))
    rc, _, err = _cli(["train"], capsys)  # -v: the traceback, then the same one line
    assert rc == 2 and "Traceback" in err and needle in err.strip().splitlines()[-1]


def test_ctrl_c_at_any_moment_is_one_line(monkeypatch, capsys, tmp_path):
    import os

    import geonav.cli

    def interrupted(*a, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(geonav.cli, "build_parser", interrupted)  # during start-up
    assert _cli(["tiles", "info", "x"], capsys)[1:] == ("", "geonav: interrupted\n")
    # ... and while the package itself is still importing, before main() exists
    fake = tmp_path / "gymnasium"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise KeyboardInterrupt\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    proc = subprocess.run([str(Path(sys.executable).parent / "geonav"), "--help"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.stderr == "geonav: interrupted\n" and proc.returncode in (-2, 130)


def test_a_toml_file_that_is_not_utf8_is_named(tmp_path, capsys, package):
    bad = tmp_path / "train.toml"
    bad.write_bytes(b"[a3c]\nlr = 0.001 # caf\xe9 latin-1\n")
    rc, _, err = _cli(["train", "--scene", package, "--tasks", tmp_path / "t.json", "--out",
                       tmp_path / "run", "--config", bad], capsys)
    _one_line_error(rc, err, f"{bad} is not UTF-8 text")
    assert "save it as UTF-8" in err
    assert not (tmp_path / "run").exists()
    exp = tmp_path / "exp.toml"
    exp.write_bytes(b'name = "caf\xe9"\n')
    rc, _, err = _cli(["experiment", "run", exp], capsys)
    _one_line_error(rc, err, f"{exp} is not UTF-8 text")


# -- 3. numbers are bounded where they enter -----------------------------------------------

@pytest.fixture(scope="module")
def tasks_json(package, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("tasks") / "t.json"
    assert main(["tasks", "make", str(package), "--kind", "scene", "--alts", "15", "--step",
                 "10", "--max-blind", "none", "-o", str(out)]) == 0
    return out


def _edited_tasks(tasks_json: Path, tmp_path: Path, edit) -> Path:
    d = json.loads(tasks_json.read_text())
    edit(d)
    out = tmp_path / "edited.json"
    out.write_text(json.dumps(d))  # json writes NaN as NaN, which Python reads back
    return out


@pytest.mark.parametrize("edit,needle", [
    (lambda d: d.update(meta="fast"), "'meta' must be an object"),
    (lambda d: d["tasks"][0].update(region_m=[0, 50]), "must be 4 finite numbers"),
    (lambda d: d["tasks"][0].update(region_m=[float("nan"), 0, 50, 50]),
     "must be 4 finite numbers"),
    (lambda d: d["tasks"][0].update(step_m=0.001), "use a step of at least"),
    (lambda d: d["tasks"][0].update(alt_m=1e300), "altitude 1e+300 m must be within"),
    (lambda d: d["tasks"][0].update(max_steps=-3), "max_steps -3 must be within"),
])
def test_task_files_out_of_bounds_are_one_line(tasks_json, package, checkpoint, tmp_path,
                                                capsys, edit, needle):
    bad = _edited_tasks(tasks_json, tmp_path, edit)
    for argv in (["tiles", "preview", package, "--tasks", bad, "-o", tmp_path / "p.png"],
                 ["eval", checkpoint, "--scene", package, "--tasks", bad]):
        rc, _, err = _cli(argv, capsys)
        _one_line_error(rc, err, needle)
    assert not (tmp_path / "p.png").exists()


def test_a_huge_lattice_is_refused_before_allocating(package, tmp_path, capsys):
    rc, _, err = _cli(_make_tasks(package, tmp_path / "t.json")[:-2] + [
        "-o", tmp_path / "t.json", "--step", "0.001"], capsys)
    _one_line_error(rc, err, "cells, more than the 1,000,000 one task may have")
    assert not (tmp_path / "t.json").exists()


def test_a_view_table_larger_than_memory_is_refused(monkeypatch):
    import geonav.vecenv
    from geonav.errors import TaskError
    from geonav.policy.testing import tiny_env_factory

    monkeypatch.setattr(geonav.vecenv, "physical_memory_bytes", lambda: 10_000)
    venv = geonav.vecenv.LatticeVecEnv(tiny_env_factory()(), 2)
    with pytest.raises(TaskError, match="GiB, more than this machine.s .* allow; use a larger"):
        venv.image_table()


@pytest.mark.parametrize("argv,needle", [
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--gsd", "1e308"],
     "--gsd 1e+308 m/px must be within"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--origin",
      "4.48,51.92,1e300"], "altitude 1e+300 m is outside"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--origin",
      "4.48,51.92,20000"], "is not a ground height"),
    (["tiles", "ingest", "{src}", "--name", "A", "--out", "{out}", "--ground-alt", "-3000"],
     "is not a ground height"),
    (["tiles", "synth", "--out", "{out}", "--size", "1e308"], "over the memory budget"),
    (["tiles", "synth", "--out", "{out}", "--size", "2", "--gsd", "1"], "give --size of at"),
    (["tiles", "synth", "--out", "{out}", "--seed", str(2**64)], "must be a seed within"),
    (["tasks", "make", "{pkg}", "-o", "{out}.json", "--seed", str(2**64)], "must be a seed"),
    (["train", "--scene", "{pkg}", "--tasks", "t.json", "--out", "{out}", "--seed", "-1"],
     "--seed"),
    (["eval", "x.pt", "--scene", "{pkg}", "--tasks", "t.json", "--seed", str(2**64)],
     "must be a seed"),
    (["fly", "x.pt", "--scene", "{pkg}", "--connect", "udpin:0.0.0.0:99999", "--target",
      "1,1"], "port 99999 is not a port"),
    (["fly", "x.pt", "--scene", "{pkg}", "--connect", "/dev/ttyACM0:99999999999",
      "--target", "1,1"], "baud rate 99999999999 is out of range"),
])
def test_numbers_out_of_bounds_are_one_line_and_nothing_written(tmp_path, capsys, utm_tif,
                                                                package, argv, needle):
    work = tmp_path / "work"
    work.mkdir()
    args = [a.format(src=utm_tif, out=work / "out", pkg=package) for a in argv]
    rc, _, err = _cli(args, capsys)
    _one_line_error(rc, err, needle)
    assert list(work.iterdir()) == []


def test_the_emulator_refuses_a_port_out_of_range():
    from geonav.errors import FlightError
    from geonav.mavlink_bridge.emulator import Emulator, EmulatorConfig

    with pytest.raises(FlightError, match="port 99999 is not a port"):
        Emulator(EmulatorConfig(listen="udp:127.0.0.1:99999")).start()


def test_experiment_without_stages_or_with_negative_seeds_is_refused(tmp_path, capsys):
    (tmp_path / "empty.toml").write_text("")
    rc, _, err = _cli(["experiment", "run", tmp_path / "empty.toml"], capsys)
    _one_line_error(rc, err, "defines no [stages.NAME] table: nothing to run")
    neg = tmp_path / "neg.toml"
    neg.write_text('seeds = [-1]\n[scenes.A]\nsynthetic = "residential"\n[tasks.t]\n'
                   'scene = "A"\n[stages.s]\nmode = "train"\ntasks = "t"\n')
    rc, _, err = _cli(["experiment", "run", neg], capsys)
    _one_line_error(rc, err, "seeds [-1] must be within 0..4294967295")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.toml", "neg.toml"]


# -- 5. cross-checks on open and at ingest --------------------------------------------------

def _copy_package(package: Path, tmp_path: Path) -> Path:
    import shutil

    out = tmp_path / "P"
    shutil.copytree(package, out, ignore=shutil.ignore_patterns(".geonav-cache"))
    return out


@pytest.mark.parametrize("key,shift,needle", [
    ("bounds_m", 30.0, "bounds_m .* is not the grid's"),
    ("bounds_wgs84", 0.01, "bounds_wgs84 .* is not the grid's"),
])
def test_hand_edited_bounds_are_refused(package, tmp_path, capsys, key, shift, needle):
    from geonav.errors import SceneError
    from geonav.scene import Scene

    out = _copy_package(package, tmp_path)
    m = json.loads((out / "scene.json").read_text())
    m[key] = [v + shift for v in m[key]]
    (out / "scene.json").write_text(json.dumps(m))
    with pytest.raises(SceneError, match=needle):
        Scene.open(out)
    rc, _, err = _cli(["tiles", "info", out], capsys)
    _one_line_error(rc, err, "edited by hand")


def test_an_ortho_that_changed_is_refused_and_verify_checks_every_open(package, tmp_path,
                                                                       capsys):
    import os

    from geonav.errors import SceneError
    from geonav.scene import Scene

    out = _copy_package(package, tmp_path)
    Scene.open(out)  # decoded and cached: intact
    ortho = out / "ortho.tif"
    st = ortho.stat()
    data = bytearray(ortho.read_bytes())
    data[-1] ^= 0xFF  # one byte, same size, same mtime: the cache still matches
    ortho.write_bytes(bytes(data))
    os.utime(ortho, ns=(st.st_atime_ns, st.st_mtime_ns))
    Scene.open(out)
    rc, _, err = _cli(["tiles", "info", out, "--verify"], capsys)
    _one_line_error(rc, err, "ortho.tif does not match its sha256")
    with open(ortho, "ab") as f:  # a file that changed visibly is checked on its decode
        f.write(b"\0" * 16)
    with pytest.raises(SceneError, match="does not match its sha256"):
        Scene.open(out)


def test_an_image_is_not_a_surface_model(tmp_path, capsys, utm_tif):
    t = Affine(1, 0, X0, 0, -1, Y0)
    grey = _write(tmp_path / "grey.tif", np.full((160, 160), 9, np.uint8), UTM31, t)
    for dsm, needle in ((utm_tif, "has 3 bands (red,green,blue)"),
                        (grey, "holds uint8 values and states no height unit")):
        rc, _, err = _cli(_ingest_argv(utm_tif, tmp_path / "S", "--dsm", dsm), capsys)
        _one_line_error(rc, err, needle)
        assert not (tmp_path / "S").exists()
    rc, _, err = _cli(_ingest_argv(utm_tif, tmp_path / "S", "--dsm", grey, "--dsm-units", "m",
                                   "--ground-alt", "0"), capsys)
    assert rc == 0, err


def test_tms_flag_against_the_exports_own_latitude(tmp_path, capsys):
    try:
        from test_tiles_support import marker_setup, write_xyz
    except ImportError:  # tests/ imported as a package
        from tests.test_tiles_support import marker_setup, write_xyz

    lon, lat, mpx, tiles = marker_setup(4.4777, 51.9244, 18)
    folder = write_xyz(tmp_path / "export", 18, tiles, mpx)
    (folder / "metadata.json").write_text(json.dumps(
        {"bounds": f"{lon - 0.001},{lat - 0.001},{lon + 0.001},{lat + 0.001}"}))
    rc, _, err = _cli(_ingest_argv(folder, tmp_path / "S", "--tms"), capsys)
    _one_line_error(rc, err, "drop --tms")
    assert not (tmp_path / "S").exists()
    assert _cli(_ingest_argv(folder, tmp_path / "S"), capsys)[0] == 0


@pytest.mark.parametrize("shape", [(1, 160), (160, 1), (1, 100_000)])
def test_too_small_rasters_are_refused_with_the_size_needed(tmp_path, capsys, shape):
    import time

    h, w = shape
    path = _write(tmp_path / "thin.tif", _texture(h, w), UTM31, Affine(0.5, 0, X0, 0, -0.5, Y0))
    t0 = time.monotonic()
    rc, _, err = _cli(_ingest_argv(path, tmp_path / "S"), capsys)
    _one_line_error(rc, err, f"is {w}x{h} px; imagery needs at least 16 px each way (8 m")
    assert time.monotonic() - t0 < 30 and not (tmp_path / "S").exists()


def test_eval_json_never_replaces_a_file_it_did_not_write(checkpoint, package, tasks_json,
                                                          tmp_path, capsys):
    mine = tmp_path / "results.json"
    mine.write_text('{"my": "results"}')
    argv = ["eval", checkpoint, "--scene", package, "--tasks", tasks_json, "--json", mine]
    rc, _, err = _cli(argv, capsys)
    _one_line_error(rc, err, "exists; pass --force")
    rc, _, err = _cli([*argv, "--force"], capsys)
    _one_line_error(rc, err, "not a geonav evaluation file")
    assert mine.read_text() == '{"my": "results"}'


@pytest.mark.parametrize("flag", ["--alt", "--max-alt"])
def test_flight_altitudes_are_bounded(package, tmp_path, capsys, flag):
    rc, _, err = _cli(["fly", "x.pt", "--scene", package, "--dry-run", "--target", "1,1",
                       flag, "1e300"], capsys)
    _one_line_error(rc, err, "m is above the 10000 m geonav flies at")


def test_a_full_disk_during_ingest_is_one_line_and_leaves_nothing(tmp_path, capsys, utm_tif,
                                                                   monkeypatch):
    import rasterio as rio
    from rasterio._err import CPLE_FileIOError

    real_open = rio.open

    def full_disk(path, mode="r", *args, **kw):
        if mode == "w" and str(path).endswith("ortho.tif"):
            raise CPLE_FileIOError(3, 3, f"{path}: No space left on device")
        return real_open(path, mode, *args, **kw)

    monkeypatch.setattr(rio, "open", full_disk)
    rc, _, err = _cli(_ingest_argv(utm_tif, tmp_path / "S"), capsys)
    _one_line_error(rc, err, "cannot write the scene package")
    assert "No space left on device" in err and "free disk space" in err
    assert list(tmp_path.iterdir()) == []  # no temp folder, no lock file, no package


def test_a_curriculum_never_removes_a_stage_folder_it_did_not_write(package, tasks_json,
                                                                     tmp_path):
    from geonav.errors import ConfigError
    from geonav.policy.curriculum import CurriculumConfig, run_curriculum
    from geonav.policy.envs import EnvFactory
    from geonav.policy.isar import ISARConfig

    out = tmp_path / "cur"
    stage = out / "stage_0_45m"
    stage.mkdir(parents=True)
    (stage / "field-notes.txt").write_text("mine")
    f = EnvFactory(str(package), str(tasks_json), obs_size_px=32)
    cfg = CurriculumConfig(levels_m=(45.0,), stage_episodes=2, teacher="none")
    with pytest.raises(ConfigError, match=r"holds files a curriculum stage does not write "
                                          r"\(field-notes.txt\)"):
        run_curriculum(f, None, "isar", ISARConfig(workers=0, seed=0), cfg, out_dir=out)
    assert (stage / "field-notes.txt").read_text() == "mine"
    proc = _holding_lock(out)  # another curriculum, its first stage not yet checkpointed
    try:
        with pytest.raises(OutputBusy, match="being written by another geonav"):
            run_curriculum(f, None, "isar", ISARConfig(workers=0, seed=0), cfg, out_dir=out)
    finally:
        proc.communicate("\n", timeout=30)
    assert (stage / "field-notes.txt").read_text() == "mine"


def test_the_demo_never_replaces_files_it_did_not_write(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text('{"my": "summary"}')
    rc, _, err = _cli(["demo", "--out", out, "--size", "400"], capsys)
    _one_line_error(rc, err, "it is not a summary geonav demo wrote")
    assert sorted(p.name for p in out.iterdir()) == ["summary.json"]


def test_synth_keep_sources_replaces_only_its_own_geotiffs(tmp_path, capsys):
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "residential-0-3857.tif").write_text("my own raster, same name")
    argv = ["tiles", "synth", "--out", tmp_path / "S", "--size", "200", "--gsd", "1",
            "--keep-sources", keep]
    rc, _, err = _cli(argv, capsys)
    _one_line_error(rc, err, "not a GeoTIFF that geonav tiles synth wrote")
    assert (keep / "residential-0-3857.tif").read_text() == "my own raster, same name"
    (keep / "residential-0-3857.tif").unlink()
    assert _cli(argv, capsys)[0] == 0
    assert _cli([*argv[:3], tmp_path / "S2", *argv[4:]], capsys)[0] == 0  # its own: replaced


def test_a_second_fetch_into_the_same_cache_is_refused(tmp_path):
    from geonav.tiles.fetch import fetch_tiles

    proc = _holding_lock(tmp_path / "cache")  # another fetch, its partial files in flight
    try:
        with pytest.raises(OutputBusy, match="being written by another geonav"):
            fetch_tiles("http://127.0.0.1:9/{z}/{x}/{y}.png", (4.0, 51.0, 4.001, 51.001), 18,
                        tmp_path / "cache", attribution="test")
    finally:
        proc.communicate("\n", timeout=30)


def test_a_folder_under_a_read_only_parent_is_locked_inside(tmp_path, monkeypatch):
    import os

    import geonav.outputs as outputs

    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setattr(outputs.os, "access", lambda p, mode: Path(p) != tmp_path)
    with outputs.output_lock(run) as lock:
        assert lock == run / ".geonav-lock" and lock.exists()
    assert list(run.iterdir()) == [] and os.listdir(tmp_path) == ["run"]
