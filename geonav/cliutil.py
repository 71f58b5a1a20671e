"""Helpers shared by the CLI faces (``geonav`` and its subcommand modules).

The root :mod:`geonav.cli` imports the subcommand modules; they take what they
share from here, so no module imports the root CLI and no two faces import
each other. Heavy imports (tqdm, torch) stay inside the functions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from geonav.errors import ConfigError


def progress_bar(desc: str) -> Callable[[str, float], None]:
    """A progress callback (phase, fraction) drawn with tqdm on stderr."""
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
            return tomllib.load(f)
    except FileNotFoundError as err:
        raise ConfigError(f"config file {path} does not exist") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path} is not valid TOML: {err}") from err


class TqdmProgress:
    """Turns trainer callbacks into a tqdm bar (success-rate moving average in the postfix)."""

    def __init__(self, disable: bool) -> None:
        from tqdm import tqdm  # type: ignore[import-untyped]

        from geonav.policy.callbacks import Callback

        class _CB(Callback):
            def on_train_start(cb, info: dict[str, Any]) -> None:
                cb.bar = tqdm(total=info["episodes"], initial=info["start_episode"],
                              unit="ep", disable=disable, dynamic_ncols=True)
                cb.recent: list[float] = []

            def on_episode(cb, record: dict[str, Any]) -> None:
                cb.recent = (cb.recent + [float(record["success"])])[-100:]
                cb.bar.update(1)
                cb.bar.set_postfix(sr=f"{sum(cb.recent) / len(cb.recent):.2f}",
                                   len=record["length"])

            def on_train_end(cb, result: Any) -> None:
                if hasattr(cb, "bar"):
                    cb.bar.close()

        self.callback = _CB()
