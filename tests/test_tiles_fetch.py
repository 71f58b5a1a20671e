"""``geonav tiles fetch`` against a local HTTP server on 127.0.0.1: a full download,
404 (masked, counted, not asked again), 429/500 (retried, then given up with the count),
a hanging server (timeout), 401 (stop), the max-tiles guard, and an interrupted run
(killed mid-download) that resumes with no partial files in the cache."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings

import pytest

from geonav.errors import GeonavWarning, TileError
from geonav.tiles.fetch import FetchIncomplete, fetch_tiles, tiles_in_bbox
from geonav.tiles.xyz import SIDECAR, read_xyz

try:
    from test_tiles_support import (
        encode,
        expected_px,
        find_marker,
        global_px_to_lonlat,
        marker_setup,
        tile_image,
        tile_server,
    )
except ImportError:  # tests/ imported as a package
    from tests.test_tiles_support import (
        encode,
        expected_px,
        find_marker,
        global_px_to_lonlat,
        marker_setup,
        tile_image,
        tile_server,
    )

Z = 18
LON, LAT = 4.4777, 51.9244
ATTR = "Test imagery (c) nobody, CC0"
FAST = dict(backoff_s=0.01, max_backoff_s=0.05, timeout_s=2.0)


@pytest.fixture(scope="module")
def setup():
    lon, lat, mpx, tiles = marker_setup(LON, LAT, Z)
    xs, ys = [t[0] for t in tiles], [t[1] for t in tiles]
    # a bbox strictly inside the 3x3 tile block
    w, n = global_px_to_lonlat(min(xs) * 256 + 10, min(ys) * 256 + 10, Z)
    e, s = global_px_to_lonlat((max(xs) + 1) * 256 - 10, (max(ys) + 1) * 256 - 10, Z)
    return dict(lon=lon, lat=lat, mpx=mpx, tiles=tiles, bbox=(w, s, e, n))


def _parse(path: str):
    parts = path.split("?")[0].strip("/").split("/")
    z, x, y = int(parts[-3]), int(parts[-2]), int(parts[-1].split(".")[0])
    return z, x, y


def _png(path: str, mpx) -> bytes:
    z, x, y = _parse(path)
    return encode(tile_image(x, y, z, mpx), "png")


def test_bbox_tiles_and_guard(setup):
    assert sorted(tiles_in_bbox(setup["bbox"], Z)) == sorted((Z, x, y) for x, y in setup["tiles"])
    with pytest.raises(TileError, match="needs 9 tiles, more than --max-tiles 8"):
        fetch_tiles("http://127.0.0.1:9/{z}/{x}/{y}.png", setup["bbox"], Z, "/nonexistent",
                    attribution=ATTR, max_tiles=8)
    with pytest.raises(TileError, match="attribution is required"):
        fetch_tiles("http://127.0.0.1:9/{z}/{x}/{y}.png", setup["bbox"], Z, "/nonexistent",
                    attribution=" ")


def test_fetch_then_ingest_with_404_masked(tmp_path, setup):
    missing = setup["tiles"][0]

    def respond(path, nth):
        z, x, y = _parse(path)
        if (x, y) == missing:
            return 404, b"", {}
        return 200, _png(path, setup["mpx"]), {"Content-Type": "image/png"}

    cache = tmp_path / "cache"
    with tile_server(respond) as (base, log):
        result = fetch_tiles(base + "/tiles/{z}/{x}/{y}.png?key=SECRET", setup["bbox"], Z, cache,
                             attribution=ATTR, workers=3, **FAST)
        assert (result.downloaded, result.not_found, result.failed) == (8, 1, 0)
        assert all("geonav/" in line for line in log)  # User-Agent sent
        n_requests = len(log)
        # rerun: everything cached, the 404 is remembered and not asked again
        again = fetch_tiles(base + "/tiles/{z}/{x}/{y}.png?key=SECRET", setup["bbox"], Z, cache,
                            attribution=ATTR, **FAST)
        assert (again.cached, again.downloaded, again.not_found) == (8, 0, 1)
        assert len(log) == n_requests
    sidecar = json.loads((cache / SIDECAR).read_text())
    assert sidecar["attribution"] == ATTR and "SECRET" not in (cache / SIDECAR).read_text()
    assert sidecar["not_found"][str(Z)] == [list(missing)]
    with pytest.warns(GeonavWarning):
        from geonav.tiles.ingest import ingest

        scene = ingest([cache], name="f", out=tmp_path / "scene", compress="DEFLATE")
    assert scene.manifest["attribution"] == ATTR
    assert scene.manifest["sources"][0]["tiles"] == 8
    assert scene.manifest["sources"][0]["tiles_missing"] == 1
    col, row = find_marker(scene.rgb, scene.mask)
    ecol, erow = expected_px(scene, setup["lon"], setup["lat"])
    assert abs(col - ecol) < 0.5 and abs(row - erow) < 0.5


def test_429_and_500_retry_then_succeed_or_give_up(tmp_path, setup):
    flaky, broken = setup["tiles"][1], setup["tiles"][2]

    def respond(path, nth):
        z, x, y = _parse(path)
        if (x, y) == flaky and nth <= 2:
            return 429, b"slow down", {"Retry-After": "0"}
        if (x, y) == broken:
            return 500, b"oops", {}
        return 200, _png(path, setup["mpx"]), {}

    cache = tmp_path / "cache"
    with tile_server(respond) as (base, log):
        with pytest.raises(FetchIncomplete, match=r"1 of 9 tiles failed after 3 retries") as err:
            fetch_tiles(base + "/{z}/{x}/{y}.png", setup["bbox"], Z, cache, attribution=ATTR,
                        retries=3, **FAST)
        r = err.value.result
        assert (r.downloaded, r.failed, r.not_found) == (8, 1, 0)
        assert "HTTP 500" in r.failures[0]
        assert sum(f"/{broken[0]}/{broken[1]}.png" in line for line in log) == 4  # 1 + 3 retries
        assert sum(f"/{flaky[0]}/{flaky[1]}.png" in line for line in log) == 3
    assert (cache / str(Z) / str(flaky[0]) / f"{flaky[1]}.png").is_file()
    assert not (cache / str(Z) / str(broken[0]) / f"{broken[1]}.png").exists()


def test_hanging_server_times_out(tmp_path, setup):
    slow = setup["tiles"][4]

    def respond(path, nth):
        z, x, y = _parse(path)
        if (x, y) == slow:
            return 0, b"", {"hang_s": 5}
        return 200, _png(path, setup["mpx"]), {}

    t0 = time.monotonic()
    with tile_server(respond) as (base, log):
        with pytest.raises(FetchIncomplete, match="1 of 9") as err:
            fetch_tiles(base + "/{z}/{x}/{y}.png", setup["bbox"], Z, tmp_path / "c",
                        attribution=ATTR, retries=1, backoff_s=0.01, timeout_s=0.4)
    assert "timeout" in err.value.result.failures[0] or "timed out" in \
        err.value.result.failures[0]
    assert time.monotonic() - t0 < 4.0


def test_refused_access_stops(tmp_path, setup):
    with tile_server(lambda path, nth: (403, b"", {})) as (base, log):
        with pytest.raises(TileError, match="refused access .HTTP 403"):
            fetch_tiles(base + "/{z}/{x}/{y}.png", setup["bbox"], Z, tmp_path / "c",
                        attribution=ATTR, workers=1, **FAST)
        assert len(log) < 9


def test_not_an_image_is_not_cached(tmp_path, setup):
    with tile_server(lambda path, nth: (200, b"<html>login</html>", {})) as (base, log):
        with pytest.raises(FetchIncomplete, match="9 of 9"):
            fetch_tiles(base + "/{z}/{x}/{y}.png", setup["bbox"], Z, tmp_path / "c",
                        attribution=ATTR, **FAST)
    assert not list((tmp_path / "c").rglob("*.png"))


_CHILD = """
import sys
from geonav.tiles.fetch import fetch_tiles
bbox = tuple(float(v) for v in sys.argv[3].split(","))
fetch_tiles(sys.argv[1], bbox, int(sys.argv[4]), sys.argv[2], attribution="x", workers=4,
            timeout_s=30.0, retries=0)
"""


def test_killed_fetch_leaves_no_partial_tiles_and_resumes(tmp_path, setup):
    """SIGKILL a fetch while a tile body is half sent; rerun completes the cache."""
    stall = {setup["tiles"][5], setup["tiles"][6]}
    healthy = {"on": False}

    def respond(path, nth):
        z, x, y = _parse(path)
        body = _png(path, setup["mpx"])
        if (x, y) in stall and not healthy["on"]:
            return 200, body, {"trickle_s": 20}  # half a body, then silence
        return 200, body, {}

    cache = tmp_path / "cache"
    template_path = "/{z}/{x}/{y}.png"
    with tile_server(respond) as (base, log):
        bbox = ",".join(repr(v) for v in setup["bbox"])
        child = subprocess.Popen([sys.executable, "-c", _CHILD, base + template_path, str(cache),
                                  bbox, str(Z)], env=dict(os.environ))
        try:
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                done = list(cache.rglob("*.png")) if cache.exists() else []
                if len(done) >= 7 and sum("/18/" in line for line in log) >= 9:
                    break
                time.sleep(0.05)
            assert child.poll() is None, "the fetch should still be waiting on stalled tiles"
        finally:
            child.send_signal(signal.SIGKILL)
            child.wait(10)
        files = list(cache.rglob("*.png"))
        assert len(files) == 7
        for f in files:  # every tile under its final name is complete
            assert f.read_bytes().endswith(b"IEND\xaeB`\x82")
        healthy["on"] = True
        # what a kill between write and rename would leave behind
        stale = files[0].parent / f".{files[0].name}.x1y2.part"
        stale.write_bytes(b"\x89PNG half")
        n_before = len(log)
        result = fetch_tiles(base + template_path, setup["bbox"], Z, cache, attribution="x",
                             **FAST)
        assert (result.cached, result.downloaded) == (7, 2)
        assert len(log) - n_before == 2  # only the missing tiles were requested
    assert not [p for p in cache.rglob("*") if p.name.endswith(".part")]
    with warnings.catch_warnings():
        warnings.simplefilter("error", GeonavWarning)  # no corrupt tile warnings
        src = read_xyz(cache)
    assert src.info["tiles"] == 9 and src.mask.all()


def test_cli_fetch(tmp_path, setup, capsys):
    from geonav.cli import main

    with tile_server(lambda path, nth: (200, _png(path, setup["mpx"]), {})) as (base, log):
        bbox = ",".join(repr(v) for v in setup["bbox"])
        args = ["tiles", "fetch", base + "/{z}/{x}/{y}.png", "--bbox", bbox, "--zoom", str(Z),
                "--out", str(tmp_path / "c"), "--attribution", ATTR, "--user-agent", "ua-test/1"]
        assert main(args) == 0
        assert "9 downloaded" in capsys.readouterr().out
        assert all(line.endswith("ua-test/1") for line in log)
        assert main(args + ["--max-tiles", "3"]) == 2
        assert "more than --max-tiles 3" in capsys.readouterr().err
