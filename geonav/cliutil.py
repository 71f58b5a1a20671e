"""Helpers shared by the CLI faces (``geonav`` and its subcommand modules).

The root :mod:`geonav.cli` imports the subcommand modules; they take what they
share from here, so no module imports the root CLI and no two faces import
each other. Heavy imports (tqdm, torch) stay inside the functions.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import warnings
from collections.abc import Callable
from typing import Any, NoReturn

from geonav.errors import ConfigError

QUIET = False
"""``geonav -q``: no progress at all and no warnings; results and errors only (set by
:func:`apply_verbosity`)."""


def progress_bar(desc: str, disable: bool = False) -> Callable[[str, float], None]:
    """A progress callback (phase, fraction): a tqdm bar on a terminal, else a line on
    stderr every ~30 s (``GEONAV_PROGRESS_S``); nothing with ``disable``
    (``--no-progress``) or ``geonav -q``."""
    if disable or QUIET:
        return lambda phase, fraction: None
    if not is_terminal():
        return _progress_lines(desc)
    from tqdm import tqdm

    bars: dict[str, tqdm] = {}

    def update(phase: str, fraction: float) -> None:
        bar = bars.get(phase)
        if bar is None:
            bar = bars[phase] = tqdm(total=1000, desc=f"{desc}: {phase}", leave=False,
                                     unit="‰", disable=None)
        bar.n = int(max(0.0, min(1.0, fraction)) * 1000)
        bar.refresh()
        if fraction >= 1.0:
            bar.close()

    return update


class _ProgressLines:
    """:func:`progress_bar` for logs: a '<desc>: <phase> 42% (95 s)' line every ~30 s
    (``GEONAV_PROGRESS_S``) while a phase runs, none for a step shorter than that, no
    carriage returns. A phase that blocks in one long call (a reprojection, the chance
    figures of a task set) still gets its lines: a daemon thread writes them while the
    latest phase is unfinished (fraction < 1)."""

    def __init__(self, desc: str) -> None:
        import threading
        import time

        self.desc = desc
        self.lines = LineProgress()
        self.t0 = time.monotonic()
        self.phase: str | None = None
        self.fraction = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __call__(self, phase: str, fraction: float) -> None:
        import threading

        with self._lock:
            self.phase, self.fraction = phase, max(0.0, min(1.0, float(fraction)))
        self._tick()
        if self._thread is None and self.fraction < 1.0:
            self._thread = threading.Thread(target=self._beat, name="geonav-progress",
                                            daemon=True)
            self._thread.start()

    def _tick(self) -> None:
        import time

        with self._lock:
            if self.phase is None or self.fraction >= 1.0 or not self.lines.due():
                return
            text = (f"{self.desc}: {self.phase} {100.0 * self.fraction:.0f}% "
                    f"({time.monotonic() - self.t0:.0f} s)")
        LineProgress.write(text)

    def _beat(self) -> None:
        step = min(1.0, max(0.05, self.lines.interval_s / 10.0))
        while not self._stop.wait(step):
            self._tick()

    def close(self) -> None:
        """No more lines (the command goes on with something else)."""
        self._stop.set()


def _progress_lines(desc: str) -> Callable[[str, float], None]:
    return _ProgressLines(desc)


def load_toml(path: str | None) -> dict[str, Any]:
    """The TOML file at ``path`` as a dict ({} for None); ConfigError if unreadable."""
    if path is None:
        return {}
    try:
        import tomllib
    except ModuleNotFoundError:  # pragma: no cover - Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]

    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError as err:
        raise ConfigError(f"config file {path} does not exist") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path} is not valid TOML: {err}") from err
    except OSError as err:
        raise ConfigError(f"config file {path} cannot be read: {err.strerror or err}") from err
    # Training configs hold tables only ([net], [a3c], [meta], ...): a scalar there is a
    # typo that would otherwise surface as a TypeError deep in the config code.
    for key, value in data.items():
        if not isinstance(value, dict):
            raise ConfigError(f"config file {path}: [{key}] must be a table, got "
                              f"{type(value).__name__} {value!r}; write it as [{key}] with "
                              "key = value lines under it")
    return data


def progress_interval_s() -> float:
    """Seconds between progress lines when stderr is not a terminal (GEONAV_PROGRESS_S, 30)."""
    import os

    try:
        return max(0.0, float(os.environ.get("GEONAV_PROGRESS_S", "30")))
    except ValueError:
        return 30.0


def is_terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


class LineProgress:
    """One line on stderr at most every ``interval_s`` (for logs: no carriage returns)."""

    def __init__(self, interval_s: float | None = None) -> None:
        import time

        self.interval_s = progress_interval_s() if interval_s is None else interval_s
        self._clock = time.monotonic
        self._last = self._clock()

    def due(self) -> bool:
        now = self._clock()
        if now - self._last >= self.interval_s:
            self._last = now
            return True
        return False

    @staticmethod
    def write(text: str) -> None:
        print(text, file=sys.stderr, flush=True)


def _budget(info: dict[str, Any]) -> tuple[str, int, int]:
    """What a training progress display counts: ("step", total, start) when the run has a
    step budget (it is the budget; the episode budget may be lifted), else ("ep", ...)."""
    if info.get("total_steps"):
        return "step", int(info["total_steps"]), int(info.get("start_env_steps") or 0)
    return "ep", int(info["episodes"]), int(info["start_episode"])


def _episode_budget(info: dict[str, Any]) -> str:
    """'/1000' when the run has an episode budget, '' when only steps bound it."""
    from geonav.policy.config import NO_EPISODE_LIMIT

    return "" if int(info["episodes"]) >= NO_EPISODE_LIMIT else f"/{info['episodes']}"


class TqdmProgress:
    """Turns trainer callbacks into a tqdm bar on a terminal (success-rate moving average in
    the postfix), or into one progress line every 30 s when stderr is not a terminal. The
    bar and the lines count env steps when the run has a step budget, else episodes.

    ``disable`` (``--no-progress``) silences the progress only: the run's start line (its
    budget and folder) and the periodic evaluations are still written, one line each."""

    def __init__(self, disable: bool) -> None:
        from tqdm import tqdm  # type: ignore[import-untyped]

        from geonav.policy.callbacks import Callback

        if QUIET:  # geonav -q: the result line only
            self.callback = Callback()
            return
        if disable:
            self.callback = _line_callback(Callback, per_episode=False)
            return
        if not is_terminal():
            self.callback = _line_callback(Callback)
            return

        class _CB(Callback):
            def on_train_start(cb, info: dict[str, Any]) -> None:
                cb.unit, total, start = _budget(info)
                cb.bar = tqdm(total=total, initial=start, unit=cb.unit, dynamic_ncols=True,
                              disable=None)
                cb.recent: list[float] = []
                cb.of = _episode_budget(info)

            def on_episode(cb, record: dict[str, Any]) -> None:
                cb.recent = (cb.recent + [float(record["success"])])[-100:]
                if cb.unit == "step":
                    cb.bar.update(max(0, int(record.get("env_steps") or 0) - cb.bar.n))
                    cb.bar.set_postfix(ep=f"{record['episode']}{cb.of}",
                                       sr=f"{sum(cb.recent) / len(cb.recent):.2f}")
                else:
                    cb.bar.update(1)
                    cb.bar.set_postfix(sr=f"{sum(cb.recent) / len(cb.recent):.2f}",
                                       len=record["length"])

            def on_eval(cb, row: dict[str, Any]) -> None:
                tqdm.write(_eval_line(row), file=sys.stderr)

            def on_train_end(cb, result: Any) -> None:
                if hasattr(cb, "bar"):
                    cb.bar.close()

        self.callback = _CB()


def _eval_line(row: dict[str, Any]) -> str:
    abl = f" (view-ablated {row['ablated_sr']:.2f})" \
        if row.get("ablated_sr") is not None else ""
    return (f"evaluation at episode {row['episode']}: greedy SR {row['greedy_sr']:.2f}{abl}, "
            f"sampled SR {row['sampled_sr']:.2f} from {row['starts']} starts")


def _line_callback(base: type, per_episode: bool = True) -> Any:
    """Lines for logs: the start (budget, run folder), every evaluation, and with
    ``per_episode`` a progress line every ~30 s."""
    import time

    class _Lines(base):  # type: ignore[misc, valid-type]
        def on_train_start(cb, info: dict[str, Any]) -> None:
            cb.lines = LineProgress()
            cb.unit, cb.total, start = _budget(info)
            cb.of = _episode_budget(info)
            cb.recent: list[float] = []
            cb.t0 = time.monotonic()
            where = f" into {info['out_dir']}" if info.get("out_dir") else ""
            budget = (f"env step {start}/{cb.total} (episode {info['start_episode']}{cb.of})"
                      if cb.unit == "step" else f"episode {start}/{cb.total}")
            LineProgress.write(f"training{where}: {budget}")

        def on_episode(cb, record: dict[str, Any]) -> None:
            cb.recent = (cb.recent + [float(record["success"])])[-100:]
            if per_episode and cb.lines.due():
                steps = record.get("env_steps", "?")
                at = (f"env step {steps}/{cb.total}, episode {record['episode']}{cb.of}"
                      if cb.unit == "step" else
                      f"episode {record['episode']}/{cb.total}, {steps} env steps")
                LineProgress.write(
                    f"training: {at}, training SR (last {len(cb.recent)}) "
                    f"{sum(cb.recent) / len(cb.recent):.2f}, {time.monotonic() - cb.t0:.0f} s")

        def on_eval(cb, row: dict[str, Any]) -> None:
            LineProgress.write(_eval_line(row))

    return _Lines()


# -- argparse: one-line errors, negative numbers, typed values -------------------------------

#: What starts like a negative number ("-122.3,37.7,...", "-5", "-.5") is a value, not an
#: option (the rule of Python 3.13; older argparse only accepts "-12" or "-1.5").
_NEGATIVE_LIST = re.compile(r"^-\.?\d")


class GeonavParser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line (exit 2) and whose values may be negative.

    Subparsers inherit the class (argparse passes ``parser_class=type(self)``), and every
    subcommand, at any depth, takes the options of :func:`common_options` (``-v``, ``-q``)
    wherever they are written: ``geonav -v train ...`` and ``geonav train ... -v``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_LIST
        self.register("action", "parsers", _SubParsers)

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _SubParsers(argparse._SubParsersAction):
    """Subcommand parsers that share :func:`common_options` (one parent for all)."""

    def add_parser(self, name: str, **kwargs: Any) -> Any:
        kwargs["parents"] = [common_options(), *kwargs.get("parents", [])]
        return super().add_parser(name, **kwargs)


_COMMON: argparse.ArgumentParser | None = None


def common_options(root: bool = False) -> argparse.ArgumentParser:
    """The options every ``geonav`` command takes: ``-v/--verbose`` (more log output,
    ``-vv`` debug, and the traceback of an error) and ``-q/--quiet`` (errors and results
    only: no warnings, no progress). One parent parser for all the subcommands; with
    ``root`` a fresh one whose defaults are set (the root parser's: a subcommand's copy
    has no defaults, so ``geonav -v train`` keeps the root's value)."""
    global _COMMON
    if _COMMON is not None and not root:
        return _COMMON
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_mutually_exclusive_group()
    g.add_argument("-v", "--verbose", action="count",
                   default=0 if root else argparse.SUPPRESS,
                   help="more log output (-vv for debug; the traceback of an error)")
    g.add_argument("-q", "--quiet", action="store_true",
                   default=False if root else argparse.SUPPRESS,
                   help="errors and results only: no warnings, no progress")
    if not root:
        _COMMON = p
    return p


def apply_verbosity(args: argparse.Namespace) -> int:
    """The logging level ``-v``/``-q`` ask for; records ``-q`` in :data:`QUIET` (progress
    and warnings off)."""
    import logging

    global QUIET
    QUIET = bool(getattr(args, "quiet", False))
    if QUIET:
        return logging.ERROR
    return logging.WARNING - 10 * min(int(getattr(args, "verbose", 0) or 0), 2)


def needs_subcommand(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    """The handler of a command group given no subcommand (``geonav``, ``geonav tiles``):
    its help on stderr and exit status 2, as a missing argument."""
    def handler(args: argparse.Namespace) -> int:
        parser.print_help(sys.stderr)
        print(f"{parser.prog}: error: give a command (see above)", file=sys.stderr)
        return 2

    return handler


def add_command_group(sub: argparse._SubParsersAction, name: str, *, help: str,
                      metavar: str) -> argparse._SubParsersAction:
    """A command with subcommands of its own (``geonav NAME COMMAND``): its subparsers
    (``dest`` ``NAME_command``), and without a subcommand it prints its help and exits 2
    (:func:`needs_subcommand`)."""
    group = sub.add_parser(name, help=help)
    commands = group.add_subparsers(dest=f"{name}_command", metavar=metavar)
    group.set_defaults(handler=needs_subcommand(group))
    return commands


def _number(text: str, what: str, kind: type) -> Any:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not {what} (finite numbers only)")
    return value


def _checked(text: str, what: str, kind: type, ok: Callable[[Any], bool], must: str) -> Any:
    """:func:`_number`, refused with "``text`` must be ``must``" unless ``ok(value)``."""
    value = _number(text, what, kind)
    if not ok(value):
        raise argparse.ArgumentTypeError(f"{text!r} must be {must}")
    return value


def finite_float(text: str) -> float:
    """argparse type: any finite number (no nan/inf)."""
    return _number(text, "a finite number", float)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _checked(text, "a positive number", float, lambda v: v > 0, "> 0")


def nonneg_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _checked(text, "a number >= 0", float, lambda v: v >= 0, ">= 0")


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _checked(text, "an integer", int, lambda v: v >= 1, "an integer >= 1")


def nonneg_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _checked(text, "an integer", int, lambda v: v >= 0, "an integer >= 0")


#: Largest seed geonav accepts: a 32-bit unsigned integer, which every RNG it seeds takes
#: (torch refuses 2**64, and seeds are offset per worker and per episode).
MAX_SEED = 2**32 - 1


def seed_int(text: str) -> int:
    """argparse type: a seed, an integer within 0..2**32-1."""
    return _checked(text, "an integer", int, lambda v: 0 <= v <= MAX_SEED,
                    f"a seed within 0..{MAX_SEED}")


#: Highest altitude (m above take-off) geonav flies or plans a task at.
MAX_ALT_M = 10_000.0


def altitude_m(text: str) -> float:
    """argparse type: an altitude in metres above ground, within 0..10 km."""
    value = positive_float(text)
    if value > MAX_ALT_M:
        raise argparse.ArgumentTypeError(f"{text!r} m is above the {MAX_ALT_M:g} m geonav "
                                         "flies at; give metres above the ground")
    return value


def float_list(text: str, *, positive: bool = True) -> tuple[float, ...]:
    """'300,75,45' -> (300.0, 75.0, 45.0); at least one value, each finite (and > 0)."""
    parts = [p.strip() for p in text.split(",")]
    if not text.strip() or not all(parts):
        raise argparse.ArgumentTypeError(f"{text!r}: give comma-separated numbers like 75,45,15")
    conv = positive_float if positive else finite_float
    return tuple(conv(p) for p in parts)


def positive_floats(text: str) -> tuple[float, ...]:
    """argparse type: a non-empty comma list of numbers > 0 (altitudes, levels)."""
    return float_list(text)


def lonlat_arg(text: str) -> Any:
    """argparse type: 'lon,lat[,alt]' in degrees (and metres) -> LonLat."""
    from geonav.errors import GeoError
    from geonav.geo import LonLat

    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(f"{text!r}: give lon,lat[,alt] in degrees, "
                                         "e.g. -122.42,37.77")
    values = [finite_float(p) for p in parts]
    try:
        return LonLat(*values)
    except GeoError as err:
        raise argparse.ArgumentTypeError(f"{text!r}: {err}") from None


def bbox_arg(text: str) -> tuple[float, float, float, float]:
    """argparse type: 'west,south,east,north' in degrees, w < e, s < n, inside WGS 84."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: give west,south,east,north in degrees, "
                                         "e.g. -122.45,37.75,-122.40,37.80")
    w, s, e, n = (finite_float(p) for p in parts)
    if not (-180 <= w <= 180 and -180 <= e <= 180 and -90 <= s <= 90 and -90 <= n <= 90):
        raise argparse.ArgumentTypeError(f"{text!r}: lon must be within -180..180 and lat "
                                         "within -90..90 (lon first)")
    if not (w < e and s < n):
        raise argparse.ArgumentTypeError(f"{text!r}: need west < east and south < north")
    return w, s, e, n


# -- warnings as single lines ----------------------------------------------------------------

def one_line_warnings() -> None:
    """Show every warning as one ``warning: ...`` line on stderr; mute third-party
    deprecation noise (it is not the user's to act on)."""
    def show(message: Any, category: type, filename: str, lineno: int,
             file: Any = None, line: str | None = None) -> None:
        text = " ".join(str(message).split())
        print(f"warning: {text}", file=file or sys.stderr)

    warnings.showwarning = show
    warnings.simplefilter("ignore" if QUIET else "default")  # geonav -q: errors only
    for cat in (DeprecationWarning, PendingDeprecationWarning, FutureWarning):
        warnings.filterwarnings("ignore", category=cat)


def oserror_line(err: OSError) -> str:
    """An OSError as one line naming the path: 'cannot write out/x: Permission denied'."""
    import errno

    what = err.strerror or str(err)
    if err.errno in (errno.EEXIST, errno.ENOTDIR):
        what += " (a file stands where a folder is needed; choose another output path)"
    elif err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        what += " (choose an output path you can write to)"
    if err.filename is not None:
        return f"cannot write {err.filename}: {what}" if err.errno != errno.ENOENT else \
            f"{err.filename}: {what}"
    return what
