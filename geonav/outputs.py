"""What geonav may write where (STYLE.md rule 9).

An existing output is replaced only when the user said so (``--force``) and it is
geonav's own output of that kind: a scene package, a task file. Everything else is
refused with a message that says how to proceed. Writers hold a lock per output path
(:func:`output_lock`, a hidden ``.NAME.geonav-lock`` file beside it, locked with
``flock`` so a killed writer never leaves it held), and a second writer of the same
path is refused at once instead of silently replacing the first one's work minutes
later.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

from geonav.errors import GeonavError, OutputBusy, OutputExists

log = logging.getLogger(__name__)

LOCK_TAG = "geonav-lock"
F = TypeVar("F", bound=Callable[..., Any])

_held: dict[str, int] = {}  # lock path -> nesting depth, in this process
_held_guard = threading.Lock()


def lock_path(target: str | os.PathLike[str]) -> Path:
    """The lock file of ``target``: ``.NAME.geonav-lock`` in the same folder, or
    ``NAME/.geonav-lock`` for an existing folder whose parent only root may write."""
    full = Path(os.path.abspath(target))
    if full.parent.is_dir() and not os.access(full.parent, os.W_OK) and full.is_dir() and \
            os.access(full, os.W_OK):
        return full / f".{LOCK_TAG}"
    return full.parent / f".{full.name}.{LOCK_TAG}"


@contextmanager
def output_lock(target: str | os.PathLike[str], what: str = "output") -> Iterator[Path]:
    """Hold the write lock of ``target`` while the body writes it.

    Re-entrant within a process (a library function that locks may call another that
    locks the same path). The lock is an ``flock`` on a small file beside the target,
    released by the kernel when the process dies.

    Raises:
        OutputBusy: another live process holds the lock.
    """
    path = lock_path(target)
    key = str(path)
    with _held_guard:
        if key in _held:
            _held[key] += 1
            nested = True
        else:
            nested = False
    if nested:
        try:
            yield path
        finally:
            with _held_guard:
                _held[key] -= 1
        return
    created = _make_parents(path.parent)
    try:
        fd = _acquire(path, Path(target), what)
    except BaseException:
        _remove_empty(created)
        raise
    with _held_guard:
        _held[key] = 1
    try:
        yield path
    finally:
        with _held_guard:
            _held.pop(key, None)
        _release(path, fd)
        _remove_empty(created)


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones created, deepest first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    for d in reversed(missing):
        d.mkdir(exist_ok=True)
    return missing


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders the lock created when nothing was written into them."""
    for d in folders:
        try:
            d.rmdir()
        except OSError:
            return


def holds_output_lock(param: str, what: str = "output") -> Callable[[F], F]:
    """Decorator: the function runs under :func:`output_lock` of its argument ``param``."""
    import functools
    import inspect

    def decorate(fn: F) -> F:
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def locked(*args: Any, **kwargs: Any) -> Any:
            target = signature.bind(*args, **kwargs).arguments[param]
            with output_lock(target, what):
                return fn(*args, **kwargs)

        return locked  # type: ignore[return-value]

    return decorate


def _acquire(path: Path, target: Path, what: str) -> int | None:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX: no lock, as before
        return None
    for _ in range(50):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:  # name the output, not its lock file
            raise OSError(err.errno, err.strerror, str(target)) from err
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"pid {holder}" if holder else "another process"
            raise OutputBusy(f"{target} is being written by another geonav ({who}); wait "
                             f"for it to finish or choose another {what} path") from None
        except OSError as err:  # a file system without flock: carry on unlocked
            os.close(fd)
            log.warning("cannot lock %s (%s); writing without a lock", path, err)
            return None
        try:  # the holder before us may have removed the file as we opened it: retry
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)
    raise OutputBusy(f"cannot take the lock {path} of {target}; try again")  # pragma: no cover


def _read_pid(fd: int) -> int | None:
    try:
        return int(os.pread(fd, 32, 0).decode().strip() or 0) or None
    except (OSError, ValueError):
        return None


def _release(path: Path, fd: int | None) -> None:
    if fd is None:
        return
    try:
        path.unlink(missing_ok=True)  # while still locked: nobody can hold this inode now
    except OSError:
        pass
    os.close(fd)


# -- whose is this? ------------------------------------------------------------------------

#: What a scene package folder holds when geonav wrote it.
SCENE_FILES = frozenset({"scene.json", "ortho.tif", "dsm.tif", ".geonav-cache", f".{LOCK_TAG}"})


def _json_object(path: Path, limit_bytes: int = 256 << 20) -> dict | None:
    try:
        if path.stat().st_size > limit_bytes:
            return None
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def not_a_scene_package(path: Path) -> str | None:
    """Why ``path`` is not a scene package geonav wrote (None when it is one)."""
    if path.is_symlink() or not path.is_dir():
        return "it is not a folder"
    manifest = _json_object(path / "scene.json")
    if manifest is None or "schema_version" not in manifest or "ortho" not in manifest:
        return "it holds no geonav scene.json, so it is not a scene package"
    foreign = sorted(p.name for p in path.iterdir() if p.name not in SCENE_FILES
                     and not p.name.endswith(".aux.xml"))
    if foreign:
        shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        return f"it also holds files geonav did not write ({shown})"
    return None


def not_a_task_file(path: Path) -> str | None:
    """Why ``path`` is not a task file geonav wrote (None when it is one)."""
    if path.is_symlink() or not path.is_file():
        return "it is not a plain file"
    data = _json_object(path)
    if data is None or not isinstance(data.get("tasks"), list) or \
            "schema_version" not in data or "scene_id" not in data:
        return "it is not a geonav task file"
    return None


def not_an_evaluation(path: Path) -> str | None:
    """Why ``path`` is not an evaluation JSON geonav wrote (``geonav eval --json``)."""
    if path.is_symlink() or not path.is_file():
        return "it is not a plain file"
    data = _json_object(path)
    if data is None or not {"greedy", "sampled", "random_walk_sr"} <= set(data):
        return "it is not a geonav evaluation file"
    return None


#: Metadata that marks a picture as geonav's, by file format (matplotlib's keys).
PICTURE_METADATA = {"png": {"Software": "geonav"}, "pdf": {"Creator": "geonav"},
                    "svg": {"Creator": "geonav"}}


def not_a_geonav_picture(path: Path) -> str | None:
    """Why ``path`` is not a picture geonav drew (None when it is one)."""
    if path.is_symlink() or not path.is_file():
        return "it is not a plain file"
    if path.suffix.lower().lstrip(".") not in PICTURE_METADATA:
        return "geonav cannot tell whether it drew it"
    try:
        with path.open("rb") as f:
            head = f.read(1 << 20)
            f.seek(max(0, path.stat().st_size - (1 << 16)))
            tail = f.read()
    except OSError as err:
        return f"it cannot be read ({err.strerror})"
    if b"geonav" not in head and b"geonav" not in tail:
        return "it is not a picture geonav drew"
    return None


#: What a training run writes into its run folder (and so would overwrite there).
RUN_FILES = ("config.json", "metrics.csv", "eval.csv", "learning_curve.png", "checkpoints")


def run_folder_conflicts(folder: Path) -> tuple[list[str], bool]:
    """What a new run in ``folder`` would overwrite: (the names, whether geonav wrote them).

    An empty ``checkpoints/`` (a run killed before its first checkpoint) is no conflict.
    """
    if not folder.is_dir():
        return [], False
    names = [n for n in RUN_FILES if os.path.lexists(folder / n) and not (
        n == "checkpoints" and (folder / n).is_dir() and not any((folder / n).iterdir()))]
    config = _json_object(folder / "config.json") if "config.json" in names else None
    ours = (folder / "metrics.csv").exists() or (config is not None and "algorithm" in config)
    return names, ours


def check_replaceable(target: str | os.PathLike[str], kind: str, *, force: bool,
                      why_not: Callable[[Path], str | None],
                      error: type[GeonavError] = OutputExists) -> None:
    """Refuse to write ``target`` unless it is absent, or ``force`` and geonav's own ``kind``.

    Args:
        target: the output path.
        kind: what geonav writes there, for messages ("scene package", "task file").
        force: the user asked to replace an existing output (``--force``).
        why_not: returns why an existing path is not geonav's own ``kind`` (None if it is).
        error: the class raised (a subclass of the caller's area, e.g. SceneError).

    Raises:
        OutputExists (or ``error``): the target exists and may not be replaced.
    """
    path = Path(target)
    if not os.path.lexists(path):
        return
    if not force:
        raise error(f"{path} exists; pass --force to replace it (only a {kind} "
                           "geonav wrote is replaced) or choose another output path")
    reason = why_not(path)
    if reason is not None:
        raise error(f"refusing to replace {path}: {reason}; geonav replaces only a "
                           f"{kind} it wrote. Move it away or choose another output path")


def replace_dir(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``, replacing the folder there.

    The old folder is first renamed to a hidden sibling, so ``out`` is never a mix of
    the two, and removed only after the new one is in place.
    """
    old = None
    if os.path.lexists(out):
        old = out.parent / f".{out.name}.geonav-old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.replace(out, old)
    try:
        os.replace(tmp, out)
    except BaseException:
        if old is not None:
            os.replace(old, out)  # put the old output back
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def claim_new_folder(out: str | os.PathLike[str], first_file: str) -> tuple[Path, int]:
    """A folder for a new record that never overwrites an older one, and its open file.

    ``out`` itself when it does not exist or is empty, else the first of ``out-2``,
    ``out-3``, ... that is; ``first_file`` is created in it exclusively (``O_EXCL``),
    so two writers never share a folder.

    Returns:
        (the folder, a file descriptor of ``first_file`` open for writing).
    """
    base = Path(out)
    for n in range(1, 10_000):
        folder = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            folder.mkdir(parents=True)
        except FileExistsError:
            if not folder.is_dir() or any(folder.iterdir()):
                continue
        try:
            fd = os.open(folder / first_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            continue
        return folder, fd
    raise OutputExists(f"{base}-2 ... {base}-9999 all exist; choose another output folder")
