"""Parameter sweeps: a grid of config variants run through one backend, one summary table.

``geonav experiment sweep CONFIG --param stages.meta.alpha=1e-3,1e-2 --param ...``
expands the grid (the cartesian product of the ``--param`` values; values are
TOML literals, else strings), makes one experiment per point named
``NAME-sweep/<point>`` and hands all their units to
:func:`~geonav.experiments.runner.run_experiments`: the same runner loop,
backend, locks, retries and resume as a single experiment (no separate
scheduler). Seeds apply inside every variant (``--seeds``), so each point
gets its medians over seeds. A unit that is the same training in several
points (a swept fine-tune's unchanged parent) is trained once and linked.

Folder ``out/NAME-sweep/``: one run folder per point, ``inputs/`` (the
scenes and task sets, one copy per distinct spec, shared by the points), and
``sweep.json`` and ``sweep.md`` (a row per point, comparison and method).
"""

from __future__ import annotations

import copy
import itertools
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from geonav.errors import ConfigError
from geonav.experiments.backend import Backend
from geonav.experiments.config import ExperimentConfig, parse_config, read_toml


def parse_param(text: str) -> tuple[str, list[Any]]:
    """``"stages.a.alpha=1e-3,1e-2"`` -> ``("stages.a.alpha", [0.001, 0.01])``."""
    key, sep, values = text.partition("=")
    key = key.strip()
    if not sep or not key or not values.strip():
        raise ConfigError(f"--param {text!r}: write KEY=VALUE[,VALUE...], e.g. "
                          "stages.meta.alpha=1e-3,1e-2")
    if key.split(".")[0] == "name":
        raise ConfigError("--param name=...: the sweep names its variants itself")
    return key, [_literal(v.strip()) for v in values.split(",")]


def _literal(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _set(data: dict[str, Any], key: str, value: Any, source: str) -> None:
    parts = key.split(".")
    node = data
    for i, part in enumerate(parts[:-1]):
        nxt = node.get(part)
        if not isinstance(nxt, dict):
            raise ConfigError(f"--param {key}: [{'.'.join(parts[:i + 1])}] is not a table of "
                              f"{source or 'the config'}")
        node = nxt
    node[parts[-1]] = value


def _slug(point: dict[str, Any]) -> str:
    lasts = [k.split(".")[-1] for k in point]
    short = len(set(lasts)) == len(lasts)
    items = [f"{k.split('.')[-1] if short else k}={v!r}".replace("'", "") for k, v in
             point.items()]
    return ",".join(items).replace("/", "_").replace(" ", "")


def sweep_configs(path: str | os.PathLike[str], params: list[str],
                  overrides: dict[str, Any] | None = None
                  ) -> tuple[str, list[tuple[dict[str, Any], ExperimentConfig]]]:
    """The sweep's name and its (point, config) variants, in grid order."""
    path = Path(path)
    data = read_toml(path, overrides)
    if not params:
        raise ConfigError("a sweep needs at least one --param KEY=V1,V2")
    grid = [parse_param(p) for p in params]
    keys = [k for k, _ in grid]
    if len(set(keys)) != len(keys):
        raise ConfigError(f"--param: a key is given twice in {keys}")
    base = str(data.get("name", path.stem))
    name = f"{base}-sweep"
    variants = []
    for values in itertools.product(*(vals for _, vals in grid)):
        point = dict(zip(keys, values, strict=True))
        d = copy.deepcopy(data)
        for k, v in point.items():
            _set(d, k, v, str(path))
        d["name"] = f"{name}/{_slug(point)}"
        variants.append((point, parse_config(d, str(path))))
    return name, variants


def run_sweep(path: str | os.PathLike[str], params: list[str],
              out_root: str | os.PathLike[str] = "runs", *,
              overrides: dict[str, Any] | None = None, only: list[str] | None = None,
              jobs: int | None = None, backend: Backend | None = None,
              max_retries: int | None = None, on_event: Callable[..., None] | None = None,
              progress: Callable[[str, float], None] | None = None,
              configure: Callable[[ExperimentConfig], ExperimentConfig] | None = None,
              ) -> dict[str, Any]:
    """Run (or resume) a sweep; returns ``{"name", "folder", "params", "rows", "table"}``.

    ``configure`` may rewrite each variant (the CLI's ``--backend`` overrides).
    """
    from geonav.experiments.runner import run_experiments

    name, variants = sweep_configs(path, params, overrides)
    if configure is not None:
        variants = [(p, configure(c)) for p, c in variants]
    summaries = run_experiments([c for _, c in variants], out_root, only=only, jobs=jobs,
                                backend=backend, max_retries=max_retries, on_event=on_event,
                                progress=progress,
                                shared_inputs=Path(out_root) / name / "inputs")
    keys = list(variants[0][0])
    rows = []
    for (point, cfg), summary in zip(variants, summaries, strict=True):
        base = dict(point, variant=cfg.name.split("/", 1)[1],
                    failed_units=len(summary.get("failed", {})))
        comps = summary.get("comparisons", [])
        if not comps:
            rows.append(dict(base, comparison=None, method=None))
        for comp in comps:
            for method, rec in comp["methods"].items():
                conv = rec["convergence"]
                econv = rec.get("eval_convergence") or {}
                rows.append(dict(base, comparison=comp["name"], method=method,
                                 median_episodes=conv.get("median"),
                                 median_censored=conv.get("median_censored"),
                                 censored=conv.get("censored"), n=conv.get("n"),
                                 eval_median_episodes=econv.get("median"),
                                 eval_median_censored=econv.get("median_censored"),
                                 eval_censored=econv.get("censored"), eval_n=econv.get("n"),
                                 final_greedy_sr=rec.get("final_greedy_sr"),
                                 final_greedy_spl=rec.get("final_greedy_spl"),
                                 final_sampled_sr=rec.get("final_sampled_sr")))
    folder = Path(out_root).resolve() / name
    table = _table(keys, rows)
    (folder / "sweep.md").write_text(f"# Sweep `{name}`\n\n" + table + "\n")
    record = dict(name=name, folder=str(folder), params=keys, rows=rows, table=table)
    (folder / "sweep.json").write_text(json.dumps(record, indent=2, default=str))
    return record


def _table(keys: list[str], rows: list[dict[str, Any]]) -> str:
    head = [*keys, "comparison", "method", "e* training SR (median)", "censored",
            "e* greedy eval (median)", "censored", "final greedy SR (median)",
            "failed units"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def conv(med: float | None, censored: bool | None) -> str:
        return "n/a" if med is None else f"{med:.0f}{'+' if censored else ''}"

    for r in rows:
        cens = "" if r.get("n") is None else f"{r['censored']}/{r['n']}"
        ecens = "" if r.get("eval_n") is None else f"{r['eval_censored']}/{r['eval_n']}"
        sr = r.get("final_greedy_sr")
        cells = [*(str(r[k]) for k in keys), str(r.get("comparison") or ""),
                 str(r.get("method") or ""),
                 conv(r.get("median_episodes"), r.get("median_censored")), cens,
                 conv(r.get("eval_median_episodes"), r.get("eval_median_censored")), ecens,
                 "n/a" if sr is None else f"{sr:.2f}", str(r["failed_units"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
