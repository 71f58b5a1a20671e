"""Download XYZ tiles for a lon/lat bbox into a resumable ``{z}/{x}/{y}.ext`` cache.

No provider is built in: the user gives a URL template and states the
licence/attribution they hold (many providers' terms forbid offline use or
machine analysis of their tiles). The download is polite by construction:

* bounded concurrency (a few threads), an identifying User-Agent;
* retries with exponential backoff (honouring ``Retry-After``) on 429, 5xx
  and timeouts, then giving up with the count (:class:`FetchIncomplete`);
  401/403 stop the whole download at once;
* a ``max_tiles`` guard checked before the first request;
* 404/204 (no tile there) is recorded, masked at ingestion and not asked
  again on a rerun; a run that ends with no tile at all is an error;
* a body is cached only when it is as long as its ``Content-Length`` and decodes
  as an image (a truncated, junk or cut-off chunked body is retried, never
  cached); every read has a deadline, so a server trickling bytes cannot hold a
  tile past ``timeout_s``; ``verify=True`` re-checks (and drops) cached tiles;
* every tile is written to a temporary file and renamed into place, so an
  interrupted run leaves no partial tile and a rerun fetches only what is
  missing.

Template placeholders: ``{z}``, ``{x}``, ``{y}``, ``{-y}`` (TMS row), ``{q}``
(Bing quadkey) and ``{s}`` (one of ``subdomains``, chosen per tile). Cache
paths are built from validated integers and a fixed set of extensions only.
The cache holds ``geonav-tiles.json`` (template with query values redacted,
attribution, counts), which :func:`geonav.tiles.xyz.read_xyz` copies into the
scene manifest.
"""

from __future__ import annotations

import http.client
import json
import logging
import os
import re
import tempfile
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from geonav import __version__
from geonav.errors import TileError
from geonav.outputs import holds_output_lock
from geonav.tiles.xyz import (
    MAX_ZOOM,
    SIDECAR,
    TILE_EXTS,
    check_tile,
    decode_tile,
    flip_y,
    scan_folder,
    sniff_format,
    tile_range_for_bbox,
)

log = logging.getLogger(__name__)

USER_AGENT = f"geonav/{__version__} (+tile ingestion for drone-navigation research)"
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_KNOWN = {"z", "x", "y", "-y", "q", "s"}
_RETRY_STATUS = {429, 500, 502, 503, 504}
_MISSING_STATUS = {204, 404}
_STOP_STATUS = {401, 403}
_MAX_TILE_BYTES = 16 << 20

Progress = Callable[[str, float], None]


class FetchIncomplete(TileError):
    """Some tiles could not be downloaded after their retries; a rerun resumes.

    Attributes:
        result: the :class:`FetchResult` with the counts.
    """

    def __init__(self, message: str, result: FetchResult) -> None:
        super().__init__(message)
        self.result = result


@dataclass
class FetchResult:
    """Counts of one fetch run (tiles)."""

    folder: str
    zoom: int
    total: int = 0
    cached: int = 0
    downloaded: int = 0
    not_found: int = 0
    failed: int = 0
    retries: int = 0
    bytes: int = 0
    verified: int = 0
    invalid_removed: int = 0
    failures: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return self.failed == 0


def check_template(template: str) -> str:
    """Validate a tile URL template; returns it. TileError says what is wrong."""
    parts = urllib.parse.urlsplit(template)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise TileError(f"tile URL template {template!r} must be an http(s) URL")
    names = set(_PLACEHOLDER.findall(template))
    unknown = names - _KNOWN
    if unknown:
        raise TileError(f"tile URL template has unknown placeholder(s) "
                        f"{', '.join('{' + u + '}' for u in sorted(unknown))}; use "
                        "{z} {x} {y} {-y} {q} {s}")
    if "q" not in names and not ({"z", "x"} <= names and names & {"y", "-y"}):
        raise TileError("tile URL template needs {z}, {x} and {y} (or {-y}), or a {q} quadkey")
    return template


def quadkey(z: int, x: int, y: int) -> str:
    """Bing Maps quadkey of an XYZ tile."""
    z, x, y = check_tile(z, x, y)
    digits = []
    for i in range(z, 0, -1):
        mask = 1 << (i - 1)
        digits.append(str((1 if x & mask else 0) + (2 if y & mask else 0)))
    return "".join(digits)


def tile_url(template: str, z: int, x: int, y: int, subdomains: Sequence[str] = ("a", "b", "c")
             ) -> str:
    """The URL of tile z/x/y (XYZ numbering) from a template."""
    z, x, y = check_tile(z, x, y)
    values = {"z": str(z), "x": str(x), "y": str(y), "-y": str(flip_y(z, y))}
    if "{q}" in template:
        values["q"] = quadkey(z, x, y)
    if "{s}" in template:
        if not subdomains:
            raise TileError("the template has {s} but no subdomains were given")
        values["s"] = subdomains[(x + y) % len(subdomains)]
    return _PLACEHOLDER.sub(lambda m: values[m.group(1)], template)


def redact(template: str) -> str:
    """The template with query-string values and user info hidden (API keys stay private)."""
    parts = urllib.parse.urlsplit(template)
    query = "&".join(
        f"{k}={v}" if _PLACEHOLDER.fullmatch(v) or not v else f"{k}=REDACTED"
        for k, v in urllib.parse.parse_qsl(parts.query, keep_blank_values=True))
    netloc = parts.netloc.rsplit("@", 1)[-1]
    return urllib.parse.urlunsplit((parts.scheme, netloc, parts.path, query, ""))


def tiles_in_bbox(bbox_lonlat: Sequence[float], zoom: int) -> list[tuple[int, int, int]]:
    """All XYZ tiles (z, x, y) meeting a lon/lat bbox at ``zoom``, row by row from the north."""
    if not (isinstance(zoom, int) and 0 <= zoom <= MAX_ZOOM):
        raise TileError(f"zoom must be an integer within 0..{MAX_ZOOM}, got {zoom!r}")
    x0, y0, x1, y1 = tile_range_for_bbox(bbox_lonlat, zoom)
    return [(zoom, x, y) for y in range(y0, y1 + 1) for x in range(x0, x1 + 1)]


def tile_path(cache: Path, z: int, x: int, y: int, ext: str) -> Path:
    """``cache/z/x/y.ext`` from validated integers and a known extension only."""
    z, x, y = check_tile(z, x, y)
    if ext not in TILE_EXTS:
        raise TileError(f"unknown tile extension {ext!r}")
    return cache / str(z) / str(x) / f"{y}.{ext}"


def cached_tile(cache: Path, z: int, x: int, y: int) -> Path | None:
    """The cached file of a tile, if a complete one exists."""
    for ext in TILE_EXTS:
        path = tile_path(cache, z, x, y, ext)
        if path.is_file() and path.stat().st_size > 0:
            return path
    return None


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _remove_partials(cache: Path, zoom: int) -> int:
    # Temporary files of a run that was killed (SIGKILL, power loss) before its rename.
    removed = 0
    level = cache / str(zoom)
    if level.is_dir():
        for part in level.glob("*/.*.part"):
            part.unlink(missing_ok=True)
            removed += 1
    return removed


class _Stop(Exception):
    pass


class BadBody(ValueError):
    """A 200 answer whose body cannot be a complete tile (short, junk, cut off)."""


def _get(url: str, *, user_agent: str, timeout_s: float) -> tuple[int, bytes, dict[str, str]]:
    """One GET: (status, body, headers). Raises urllib/socket errors on failure.

    ``timeout_s`` bounds the connect, every read (socket timeout) and the whole
    body (deadline checked after each read, which returns as soon as any bytes
    arrive, so a server trickling a byte a second is cut off in time). A body
    shorter than its ``Content-Length``, or a chunked body cut short, raises
    :class:`BadBody`.
    """
    request = urllib.request.Request(url, headers={"User-Agent": user_agent,
                                                   "Accept": "image/*"})
    deadline = time.monotonic() + timeout_s
    try:
        with urllib.request.urlopen(request, timeout=timeout_s) as response:  # noqa: S310
            chunks, size = [], 0
            try:
                while chunk := response.read1(1 << 16):
                    chunks.append(chunk)
                    size += len(chunk)
                    if size > _MAX_TILE_BYTES:
                        raise BadBody(f"tile larger than {_MAX_TILE_BYTES >> 20} MiB")
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"body not complete after {timeout_s:g} s")
            except http.client.IncompleteRead as err:
                raise BadBody(f"body cut short after {size + len(err.partial)} bytes") from err
            headers = dict(response.headers)
            declared = headers.get("Content-Length", "").strip()
            if declared.isdigit() and int(declared) != size:
                raise BadBody(f"body is {size} bytes, Content-Length said {declared}")
            return response.status, b"".join(chunks), headers
    except urllib.error.HTTPError as err:
        with err:
            return err.code, b"", dict(err.headers or {})
    except http.client.HTTPException as err:  # bad status line, chunk framing, ...
        raise BadBody(f"broken HTTP answer ({type(err).__name__}: {err})") from err


def check_tile_bytes(data: bytes) -> str:
    """The image format of a complete, decodable tile; :class:`BadBody` otherwise."""
    fmt = sniff_format(data)
    if fmt is None:
        raise BadBody("answer is not a PNG/JPEG/WebP image")
    try:
        decode_tile(data)
    except ValueError as err:
        raise BadBody(str(err)) from err
    return fmt


def verify_cache(cache: str | os.PathLike[str], zoom: int | None = None,
                 tiles: Sequence[tuple[int, int, int]] | None = None) -> tuple[int, list[str]]:
    """Decode every cached tile (of ``zoom``, or of ``tiles``) and delete the bad ones.

    Returns:
        (tiles checked, names of the tiles removed); a rerun of the fetch gets those again.
    """
    cache = Path(cache)
    if not cache.is_dir():
        raise TileError(f"{cache} is not a tile cache folder")
    if tiles is not None:
        paths = [p for z, x, y in tiles if (p := cached_tile(cache, z, x, y)) is not None]
    else:
        levels = scan_folder(cache)
        paths = [p for z, level in levels.items() if zoom is None or z == zoom
                 for p in level.values()]
    removed = []
    for path in paths:
        try:
            check_tile_bytes(path.read_bytes())
        except (BadBody, OSError) as err:
            log.info("removing bad cached tile %s: %s", path, err)
            path.unlink(missing_ok=True)
            removed.append(f"{path.relative_to(cache)} ({err})")
    return len(paths), removed


@holds_output_lock("cache", "--out")  # two fetches into one cache: the second is refused
def fetch_tiles(
    template: str,
    bbox_lonlat: Sequence[float],
    zoom: int,
    cache: str | os.PathLike[str],
    *,
    attribution: str,
    max_tiles: int = 2000,
    workers: int = 4,
    subdomains: Sequence[str] = ("a", "b", "c"),
    user_agent: str = USER_AGENT,
    timeout_s: float = 20.0,
    retries: int = 4,
    backoff_s: float = 1.0,
    max_backoff_s: float = 60.0,
    retry_not_found: bool = False,
    verify: bool = False,
    progress: Progress | None = None,
) -> FetchResult:
    """Download the tiles of a lon/lat bbox at one zoom into ``cache`` (XYZ layout).

    Args:
        template: tile URL template (see the module docstring).
        bbox_lonlat: (west, south, east, north) in degrees.
        zoom: zoom level.
        cache: the cache folder; tiles already there are not fetched again.
        attribution: the licence/attribution text the user holds; required.
        max_tiles: refuse a bbox/zoom needing more tiles than this.
        workers: concurrent requests (1..16).
        subdomains: values for ``{s}``.
        user_agent: the User-Agent header.
        timeout_s: per request: connect, each read, and the whole body.
        retries: extra attempts after a 429/5xx/timeout/connection error.
        backoff_s: first backoff; doubles per attempt, capped by ``max_backoff_s``.
        max_backoff_s: longest wait, also for a server's ``Retry-After``.
        retry_not_found: ask again for tiles an earlier run found missing (404).
        verify: decode the cached tiles of the bbox first and fetch the bad ones again.
        progress: callback ("fetch", fraction).

    Returns:
        The counts; all tiles are then in the cache, or known to be missing (404).

    Raises:
        TileError: bad template/bbox/zoom, no attribution, too many tiles, or the
            server refused access (401/403).
        FetchIncomplete: tiles still failing after their retries (rerun to resume).
        TileError: nothing useful: not one tile of the bbox is cached or downloaded.
    """
    _check_fetch_args(template, attribution, workers, timeout_s, retries, max_tiles)
    tiles = tiles_in_bbox(bbox_lonlat, zoom)
    if len(tiles) > max_tiles:
        raise TileError(f"bbox {tuple(bbox_lonlat)} at zoom {zoom} needs {len(tiles)} tiles, "
                        f"more than --max-tiles {max_tiles}; use a smaller bbox or zoom, or "
                        "raise --max-tiles if the provider's terms allow it")
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    stale = _remove_partials(cache, zoom)
    if stale:
        log.info("removed %d partial files of an interrupted run from %s", stale, cache)
    sidecar = _load_sidecar(cache)
    known_missing = set() if retry_not_found else {
        tuple(t) for t in sidecar.get("not_found", {}).get(str(zoom), [])}
    result = FetchResult(str(cache), zoom, total=len(tiles))
    todo = _to_download(cache, tiles, known_missing, result, verify)
    run = _TileFetch(template, cache, subdomains, user_agent, timeout_s, retries, backoff_s,
                     max_backoff_s, progress, result,
                     missing=set(known_missing) & {(x, y) for _, x, y in tiles})
    try:
        run.download(todo, workers)
    finally:
        _save_sidecar(cache, sidecar, template=template, attribution=attribution,
                      zoom=zoom, bbox_lonlat=bbox_lonlat, missing=run.missing,
                      user_agent=user_agent, result=result)
    if progress:
        progress("fetch", 1.0)
    _raise_unless_complete(run, bbox_lonlat, retry_not_found)
    return result


def _check_fetch_args(template: str, attribution: str, workers: int, timeout_s: float,
                      retries: int, max_tiles: int) -> None:
    """TileError for a bad template or setting of :func:`fetch_tiles`, before any request."""
    check_template(template)
    if not attribution or not attribution.strip():
        raise TileError("--attribution is required: state the provider and the licence or "
                        "terms under which you may use these tiles offline")
    if not 1 <= workers <= 16:
        raise TileError(f"workers must be within 1..16, got {workers}")
    if not (isinstance(timeout_s, (int, float)) and 0 < timeout_s < float("inf")):
        raise TileError(f"timeout must be a positive number of seconds, got {timeout_s!r}")
    if not (isinstance(retries, int) and retries >= 0):
        raise TileError(f"retries must be an integer >= 0, got {retries!r}")
    if not (isinstance(max_tiles, int) and max_tiles >= 1):
        raise TileError(f"max_tiles must be an integer >= 1, got {max_tiles!r}")


def _to_download(cache: Path, tiles: list[tuple[int, int, int]],
                 known_missing: set[tuple[int, int]], result: FetchResult,
                 verify: bool) -> list[tuple[int, int, int]]:
    """The tiles not yet cached nor known to be missing (counting those into ``result``),
    after dropping bad cached tiles when ``verify``."""
    if verify:
        result.verified, bad = verify_cache(cache, tiles=tiles)
        result.invalid_removed = len(bad)
        if bad:
            log.warning("removed %d bad cached tiles (e.g. %s); fetching them again",
                        len(bad), bad[0])
    todo = []
    for z, x, y in tiles:
        if cached_tile(cache, z, x, y) is not None:
            result.cached += 1
        elif (x, y) in known_missing:
            result.not_found += 1
        else:
            todo.append((z, x, y))
    log.info("fetch: %d tiles, %d cached, %d known missing, %d to download", len(tiles),
             result.cached, result.not_found, len(todo))
    return todo


@dataclass
class _TileFetch:
    """One :func:`fetch_tiles` download: its settings, and the state its worker threads
    share (``result``, ``missing``, ``refused``; updated under ``lock``)."""

    template: str
    cache: Path
    subdomains: Sequence[str]
    user_agent: str
    timeout_s: float
    retries: int
    backoff_s: float
    max_backoff_s: float
    progress: Progress | None
    result: FetchResult
    missing: set[tuple[int, int]]
    refused: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    stop: threading.Event = field(default_factory=threading.Event)

    def download(self, todo: list[tuple[int, int, int]], workers: int) -> None:
        """Fetch ``todo`` on ``workers`` threads; Ctrl-C or a failing callback stops them."""
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="geonav-fetch") as pool:
            futures = [pool.submit(self.one, t) for t in todo]
            try:
                for future in futures:
                    future.result()
            except BaseException:
                self.stop.set()  # Ctrl-C or a failing callback: finish no new tiles
                for future in futures:
                    future.cancel()
                raise

    def one(self, tile: tuple[int, int, int]) -> None:
        """Fetch one tile with its retries and record the outcome (nothing once stopped)."""
        attempt = self._attempts(tile)
        if attempt is not None:
            self._record(tile, *attempt)

    def _attempts(self, tile: tuple[int, int, int]) -> tuple[str, str, int, int] | None:
        """(outcome, detail, bytes, retries used) of one tile's requests: "ok", "missing"
        (404/204), "refused" (401/403) or "failed"; None when the run was stopped."""
        z, x, y = tile
        url = tile_url(self.template, z, x, y, self.subdomains)
        outcome, detail, size, tries = "failed", "", 0, 0
        for attempt in range(self.retries + 1):
            if self.stop.is_set():
                return None
            tries = attempt
            wait = min(self.max_backoff_s, self.backoff_s * 2 ** attempt)
            try:
                status, body, headers = _get(url, user_agent=self.user_agent,
                                             timeout_s=self.timeout_s)
            except TimeoutError as err:
                detail = f"timeout ({err or self.timeout_s})"
            except BadBody as err:
                detail = f"bad body ({err})"
            except urllib.error.URLError as err:
                detail = f"connection error ({err.reason})"
            except (OSError, ValueError) as err:  # reset connections, oversized bodies
                detail = f"{type(err).__name__}: {err}"
            else:
                if status in _MISSING_STATUS:
                    outcome = "missing"
                    break
                if status in _STOP_STATUS:
                    outcome, detail = "refused", f"HTTP {status}"
                    break
                if status in _RETRY_STATUS:
                    detail = f"HTTP {status}"
                    retry_after = headers.get("Retry-After", "")
                    if retry_after.strip().isdigit():
                        wait = min(self.max_backoff_s, float(retry_after))
                elif status == 200:
                    try:
                        fmt = check_tile_bytes(body)
                    except BadBody as err:  # junk or a truncated image: ask again
                        detail = f"bad body ({err})"
                    else:
                        _write_atomic(tile_path(self.cache, z, x, y, fmt), body)
                        outcome, size = "ok", len(body)
                        break
                else:
                    outcome, detail = "failed", f"HTTP {status}"
                    break
            if attempt < self.retries and self.stop.wait(wait):
                return None
        return outcome, detail, size, tries

    def _record(self, tile: tuple[int, int, int], outcome: str, detail: str, size: int,
                tries: int) -> None:
        z, x, y = tile
        result = self.result
        with self.lock:
            result.retries += tries
            if outcome == "ok":
                result.downloaded += 1
                result.bytes += size
            elif outcome == "missing":
                result.not_found += 1
                self.missing.add((x, y))
            else:
                result.failed += 1
                if len(result.failures) < 10:
                    result.failures.append(f"{z}/{x}/{y}: {detail}")
                if outcome == "refused":
                    self.refused.append(detail)
                    self.stop.set()
            done = result.downloaded + result.not_found + result.failed
            if self.progress:
                self.progress("fetch", (result.cached + done) / max(1, result.total))
            if outcome != "ok":
                log.debug("tile %d/%d/%d: %s %s", z, x, y, outcome, detail)


def _raise_unless_complete(run: _TileFetch, bbox_lonlat: Sequence[float],
                           retry_not_found: bool) -> None:
    """TileError when the server refused access or nothing at all was fetched;
    FetchIncomplete when tiles still failed after their retries."""
    result, template = run.result, run.template
    if run.refused:
        raise TileError(f"the tile server refused access ({run.refused[0]}) at "
                        f"{redact(template)}; stopped after {result.downloaded} new tiles. "
                        "Check the key/terms")
    if result.failed:
        raise FetchIncomplete(
            f"{result.failed} of {result.total} tiles failed after {run.retries} retries "
            f"(e.g. {result.failures[0]}); {result.cached + result.downloaded} are cached in "
            f"{run.cache}; rerun the same command to resume", result)
    if result.cached + result.downloaded == 0:
        raise TileError(
            f"nothing fetched: all {result.total} tiles of bbox {tuple(bbox_lonlat)} at zoom "
            f"{result.zoom} are missing on the server (404/204) at {redact(template)}; check "
            "the URL template, the zoom and the bbox (lon first)"
            + ("" if retry_not_found else ", or pass --retry-missing"))


def _load_sidecar(cache: Path) -> dict[str, Any]:
    path = cache / SIDECAR
    try:
        meta = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        log.warning("ignoring unreadable %s", path)
        meta = {}
    return meta if isinstance(meta, dict) else {}


def _save_sidecar(cache: Path, meta: dict[str, Any], *, template: str, attribution: str,
                  zoom: int, bbox_lonlat: Sequence[float], missing: set[tuple[int, int]],
                  user_agent: str, result: FetchResult) -> None:
    meta = dict(meta)
    previous = meta.get("attribution")
    if previous and previous != attribution:
        log.warning("cache %s was fetched with attribution %r; now %r", cache, previous,
                    attribution)
    not_found = dict(meta.get("not_found", {}))
    not_found[str(zoom)] = sorted([x, y] for x, y in missing)
    meta.update(
        attribution=attribution,
        url_template=redact(template),
        user_agent=user_agent,
        fetched_utc=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        geonav_version=__version__,
        not_found=not_found,
    )
    runs = list(meta.get("runs", []))[-19:]
    runs.append(dict(zoom=zoom, bbox_lonlat=list(bbox_lonlat),
                     **{k: v for k, v in asdict(result).items() if k not in ("folder", "zoom")}))
    meta["runs"] = runs
    _write_atomic_text(cache / SIDECAR, json.dumps(meta, indent=2))


def _write_atomic_text(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
