"""Typed validation of config values (geonav.configcheck): a value of the wrong type in a
TOML file is one ConfigError naming the table and the field, never a TypeError."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from geonav.configcheck import build, coerce, describe
from geonav.errors import ConfigError
from geonav.experiments.config import parse_config
from geonav.policy.config import A3CConfig, NetConfig, from_dict
from geonav.policy.meta_config import CurriculumConfig, base_config

TINY = Path(__file__).resolve().parent.parent / "configs" / "tiny.toml"


@pytest.mark.parametrize(("tp", "value", "expected"), [
    (float, 1, 1.0), (int, 1e5, 100_000), (tuple[float, ...], [75, 45], (75.0, 45.0)),
    (str | None, None, None), (int | None, 3, 3), (tuple[float, float], [0.9, 1], (0.9, 1.0)),
    (dict[str, float], {"a": 2}, {"a": 2.0}), (bool, False, False),
])
def test_lossless_coercions(tp, value, expected):
    got = coerce(tp, value, "x")
    assert got == expected and type(got) is type(expected)


@pytest.mark.parametrize(("tp", "value", "words"), [
    (float, "abc", "expected a number"), (float, True, "expected a number"),
    (int, 1.5, "expected a whole number"), (bool, 1, "expected true or false"),
    (str, 3, "expected a string"), (tuple[float, ...], 3, "expected a list (a number each)"),
    (tuple[float, ...], [1, "a"], "(item 2 is 'a')"),
    (tuple[float, float], [1.0], "expected a list of 2 (a number, a number) (1 given)"),
    (str | None, 3, "expected a string (or left out)"),
])
def test_wrong_types_are_one_line_naming_the_field(tp, value, words):
    with pytest.raises(ConfigError) as err:
        coerce(tp, value, "[a3c] lr")
    assert str(err.value).startswith(f"[a3c] lr = {value!r}: ") and words in str(err.value)
    assert "\n" not in str(err.value)
    assert describe(tp) in str(err.value)


def test_policy_configs_check_their_own_types():
    # the case: a TypeError from `self.lr <= 0` in __post_init__ before
    with pytest.raises(ConfigError, match=r"^\[a3c\] lr = 'abc': expected a number$"):
        from_dict(A3CConfig, {"lr": "abc"}, "[a3c]")
    with pytest.raises(ConfigError, match=r"^A3CConfig loss gamma = 'x': expected a number"):
        from_dict(A3CConfig, {"loss": {"gamma": "x"}})
    with pytest.raises(ConfigError, match=r"^\[net\] encoder_weights = 3: expected a string"):
        from_dict(NetConfig, {"encoder_weights": 3}, "[net]")
    with pytest.raises(ConfigError, match=r"levels_m = \[75, 'a'\]: .*\(item 2 is 'a'\)"):
        from_dict(CurriculumConfig, {"levels_m": [75, "a"]})
    with pytest.raises(ConfigError, match=r"^\[isar\] alpha = '0.1': expected a number"):
        base_config("isar", {"alpha": "0.1"}, "[isar]")
    with pytest.raises(ConfigError, match=r"unknown A3CConfig option\(s\) \['learning_rate'\]"):
        from_dict(A3CConfig, {"learning_rate": 0.1})
    # ranges stay the dataclass's own, named with the table
    with pytest.raises(ConfigError, match=r"^\[a3c\]: lr must be positive, got -1.0$"):
        from_dict(A3CConfig, {"lr": -1}, "[a3c]")
    cfg = from_dict(A3CConfig, {"lr": 1, "episodes": 2e3, "adam_betas": [0.9, 0.99]})
    assert (cfg.lr, cfg.episodes, cfg.adam_betas) == (1.0, 2000, (0.9, 0.99))
    assert build(CurriculumConfig, {"levels_m": [75, 45]}).levels_m == (75.0, 45.0)


def _tiny(mutate) -> None:
    raw = tomllib.loads(TINY.read_text())
    raw = copy.deepcopy(raw)
    mutate(raw)
    parse_config(raw, "x.toml")


@pytest.mark.parametrize(("mutate", "message"), [
    (lambda d: d["stages"]["pre"].update(lr="abc"),
     "[stages.pre] lr = 'abc': expected a number"),
    (lambda d: d["stages"]["pre"].update(hidden_size=1.5),
     "[stages.pre] hidden_size = 1.5: expected a whole number"),
    (lambda d: d["stages"]["pre"].update(batch="16"),
     "[stages.pre] batch = '16': expected a whole number (or left out)"),
    (lambda d: d["stages"]["pre"].update(stop_at_convergence="yes"),
     "[stages.pre] stop_at_convergence = 'yes': expected true or false"),
    (lambda d: d["tasks"]["A_meta"].update(alt_m="high"),
     "[tasks.A_meta] alt_m = 'high': expected a number"),
    (lambda d: d["scenes"]["A"].update(size_m=[1]), "[scenes.A] size_m = [1]: expected a number"),
    (lambda d: d.update(seeds=["a"]), "x.toml seeds = ['a']: expected a list"),
    (lambda d: d["convergence"].update(window="w"),
     "x.toml [convergence] window = 'w': expected a whole number"),
])
def test_experiment_config_is_checked_before_anything_runs(mutate, message):
    """Stage options are built into their units' configs when the TOML is read: a bad
    value stops `experiment run` at once, not when its unit starts (hours in, maybe)."""
    with pytest.raises(ConfigError) as err:
        _tiny(mutate)
    assert str(err.value).startswith(message), str(err.value)


def test_cli_train_config_of_the_wrong_type_is_one_line(tmp_path, capsys):
    from geonav.cli import main

    toml = tmp_path / "c.toml"
    toml.write_text('[a3c]\nlr = "abc"\n')
    code = main(["train", "--scene", "s", "--tasks", "t", "--out", str(tmp_path / "r"),
                 "--config", str(toml)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == ["geonav: error: [a3c] lr = 'abc': expected a number"]
    assert not (tmp_path / "r").exists()


def test_a_partial_nested_table_keeps_the_parents_default():
    """``[ppo.loss] beta = 0`` changes the entropy weight only: PPO's GAE lambda and
    discount stay 0.95 (its ``loss`` default), not LossConfig's class defaults 1.0 and
    0.99; A3C's stay those."""
    from geonav.policy.batched.ppo import PPOConfig
    from geonav.policy.config import A3CConfig, LossConfig, from_dict

    ppo = from_dict(PPOConfig, {"loss": {"beta": 0.0}})
    assert ppo.loss == LossConfig(gamma=0.95, tau=0.95, beta=0.0,
                                  bootstrap_on_truncation=True)
    assert from_dict(PPOConfig, {"loss": {"gamma": 0.99}}).loss == LossConfig(
        gamma=0.99, tau=0.95, bootstrap_on_truncation=True)  # configs/real.toml's pin
    assert from_dict(A3CConfig, {"loss": {"beta": 0.0}}).loss == LossConfig(beta=0.0)
    full = {"gamma": 0.9, "tau": 0.5, "beta": 0.1, "value_coef": 1.0,
            "bootstrap_on_truncation": True}
    assert from_dict(PPOConfig, {"loss": full}).loss == LossConfig(**full)
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(PPOConfig, {"loss": {"betta": 0.0}})
