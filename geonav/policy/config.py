"""Configuration dataclasses of the policy package (CleanRL style: a docstring per field).

Every field's docstring becomes its ``--help`` text in the CLI, and the resolved
config of a run is written as JSON into the run folder (STYLE.md rule 5).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from typing import Any

from geonav.errors import ConfigError

ENCODERS = ("cnn", "random", "resnet18", "corr")
NO_EPISODE_LIMIT = 1_000_000_000
"""The episode budget of a run given a step budget and no episode budget (``--total-steps``
without ``--episodes``, or ``total_steps`` without ``episodes`` in a TOML table): the
steps are the budget (:func:`step_budget_first`)."""
INITS = ("orthogonal", "savn")
INPUT_NORMS = ("center", "none")
CNN_KINDS = ("small", "nature")


@dataclass(frozen=True)
class NetConfig:
    """Architecture of the actor-critic (ALGORITHMS.md 4.0)."""

    encoder: str = "cnn"
    """Image encoder: 'cnn' (small CNN trained end to end), 'random' (frozen random CNN,
    cached features; tests and benchmarks), 'resnet18' (frozen, needs geonav[resnet]) or
    'corr' (frozen and parameter-free: each view's features are its normalised
    cross-correlation with the episode's target view over ``corr_radius`` shifts; beyond
    the paper, see docs/learning.md §8)."""
    cnn: str = "small"
    """Layers of the trainable CNN (encoder='cnn'): 'small' (two convolutions, 16 and 32
    channels; the default) or 'nature' (three, 32/64/64, SB3's NatureCNN); see
    docs/learning.md §14."""
    encoder_weights: str | None = None
    """ResNet18 weights: a local state_dict file; None downloads torchvision's pretrained ones."""
    obs_size_px: int = 84
    """Side of the square observation in pixels (N); must match the environment's camera."""
    embed_dim: int = 64
    """Size of the current-view and target-view embeddings."""
    action_embed_dim: int = 10
    """Size of the previous-action-probabilities embedding."""
    hidden_size: int = 128
    """Width of the fully connected layer after the concatenation."""
    lstm_size: int = 128
    """Hidden size of the LSTMCell. The paper gives none; SAVN uses 512. 128 keeps a batch-1
    step's LSTM weights in cache: 2x faster steps than 256 on a small CPU (bench/)."""
    n_actions: int = 4
    """Number of discrete actions (GeoNavEnv: forward, right, left, backward)."""
    random_encoder_seed: int = 0
    """Seed of the frozen random CNN's weights (encoder='random')."""
    corr_radius: int = 12
    """encoder='corr': the largest shift compared, in pixels of the half-resolution grey
    view (so +-2 * corr_radius view pixels); the features are (2 * corr_radius + 1)^2."""
    input_norm: str = "center"
    """Image scaling before the CNN encoders ('cnn', 'random'): 'center' maps uint8 to
    (x/255 - 0.5)/0.25; 'none' to [0, 1] (geonav <= 0.1; ResNet18 always uses ImageNet's
    normalisation). Centred inputs are one of the three fixes of issue 10."""
    init: str = "orthogonal"
    """Weight initialisation: 'orthogonal' (conv/linear layers orthogonal with ReLU gain
    sqrt(2), LSTM orthogonal, zero biases; keeps activations O(1) through the trunk) or
    'savn' (allenai/savn: Xavier-uniform, which halves the signal at every ReLU layer)."""
    actor_init_std: float | None = None
    """Row norm of the actor head's initial weights; None: 1.0 for init='orthogonal', 0.01
    for 'savn'. At 0.01 the policy gradient reaching the image layers is 100x smaller
    than the critic's and a state-blind action bias wins (issue 10); 1.0 lets the
    image-dependent part of the policy learn first."""
    recurrent: bool = True
    """True: the paper's network (an LSTM cell after the FC layer, fed the previous action
    probabilities). False: no LSTM and no previous-action input; the FC layer's output
    feeds the heads, so the policy is a function of the current and target views alone
    (enough on geonav's fully observed tasks), and PPO can draw its minibatches from single
    steps instead of whole slot sequences (docs/learning.md §14)."""
    separate_critic: bool = False
    """Feed-forward networks only (``recurrent = False``): the critic gets its own FC layer
    of ``hidden_size`` over the same view embeddings, as SB3's separate policy and value
    MLPs, instead of sharing the actor's (docs/learning.md §14, stop 43). Stored as one FC
    layer of 2 x ``hidden_size`` outputs, the actor reading the first half and the critic
    the second, which is the same map as two layers."""
    prev_view_input: bool = False
    """Add the extra input slot E(o^prev) (ALGORITHMS.md (e), option B): the encoder features
    of the view at the same cell at the previous curriculum stage's altitude, embedded by
    its own linear layer to embed_dim and concatenated before the FC layer. Zero-filled
    where no previous-altitude view exists (stage 0, meta-training, flight). Needed by
    the curriculum's teacher='input'; False keeps the original architecture."""

    def __post_init__(self) -> None:
        if self.encoder not in ENCODERS:
            raise ConfigError(f"encoder must be one of {ENCODERS}, not {self.encoder!r}")
        if self.encoder == "corr":
            if not 1 <= self.corr_radius < self.obs_size_px // 2:
                raise ConfigError(f"corr_radius must be in 1..{self.obs_size_px // 2 - 1} "
                                  f"for {self.obs_size_px} px views, got {self.corr_radius}")
            if self.prev_view_input:
                raise ConfigError("encoder 'corr' compares a view with the episode's target; "
                                  "the previous-view slot (prev_view_input) is not supported "
                                  "with it")
        if not 16 <= self.obs_size_px <= 1024:
            raise ConfigError(f"obs_size_px must be within 16..1024, got {self.obs_size_px}")
        if self.input_norm not in INPUT_NORMS:
            raise ConfigError(f"input_norm must be one of {INPUT_NORMS}, not {self.input_norm!r}")
        if self.cnn not in CNN_KINDS:
            raise ConfigError(f"cnn must be one of {CNN_KINDS}, not {self.cnn!r}")
        if self.encoder == "cnn" and self.cnn == "nature" and self.obs_size_px < 36:
            raise ConfigError(f"the 'nature' CNN needs views of >= 36 px, got "
                              f"{self.obs_size_px}")
        if self.init not in INITS:
            raise ConfigError(f"init must be one of {INITS}, not {self.init!r}")
        if self.actor_init_std is not None and not self.actor_init_std > 0:
            raise ConfigError(f"actor_init_std must be positive, got {self.actor_init_std}")
        if self.separate_critic and self.recurrent:
            raise ConfigError("separate_critic needs a feed-forward network (recurrent = "
                              "false): the recurrent network's heads share its LSTM")
        for name in ("embed_dim", "action_embed_dim", "hidden_size", "lstm_size", "n_actions"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class LossConfig:
    """The segment actor-critic loss L_AC (ALGORITHMS.md 4.0)."""

    gamma: float = 0.99
    """Discount factor."""
    tau: float = 1.0
    """GAE lambda."""
    beta: float = 0.01
    """Entropy bonus weight."""
    value_coef: float = 0.5
    """Weight of the value loss in L = policy + value_coef * value."""
    bootstrap_on_truncation: bool = False
    """Bootstrap with V(s) on a time-limit truncation (truncation-correct); False follows SAVN,
    which treats a timeout as done and bootstraps 0."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.gamma <= 1.0 or not 0.0 <= self.tau <= 1.0:
            raise ConfigError(f"gamma and tau must lie in [0, 1], got {self.gamma}, {self.tau}")


@dataclass(frozen=True)
class A3CConfig:
    """A3C training (ALGORITHMS.md (a))."""

    episodes: int = 1000
    """Training episodes in total, counted over all workers (including resumed ones). With
    a step budget and no episode budget given, the steps are the budget (the command line
    and TOML tables lift this default)."""
    total_steps: int = 0
    """Env-step budget in total (including resumed steps; 0: none). Training ends at
    whichever budget, episodes or steps, runs out first (at an episode end)."""
    workers: int = 2
    """Worker processes; 0 runs the deterministic single-process mode."""
    t_max: int = 15
    """Steps per rollout between updates (K*N = 15, as often as ISAR's adaptive updates)."""
    lr: float = 1e-4
    """Learning rate of the shared Adam."""
    lr_warmup: int = 0
    """Optimiser steps over which the rate ramps linearly up to ``lr`` (0: none). Meant for
    fine-tuning a trained policy, where a fresh Adam's first steps are about ``lr`` on every
    weight whatever the gradient."""
    adam_eps: float = 1e-3
    """Adam epsilon (SAVN's SharedAdam)."""
    adam_betas: tuple[float, float] = (0.9, 0.999)
    """Adam betas."""
    amsgrad: bool = True
    """AMSGrad variant, as SAVN's SharedAdam."""
    fused: bool = True
    """Use the fused Adam kernel (several times faster steps on CPU)."""
    max_grad_norm: float = 100.0
    """Gradient-norm clip per update."""
    seed: int = 0
    """Seed of torch, numpy and the environment (worker i uses seed + 1000 * i)."""
    checkpoint_every: int = 500
    """Write checkpoints/latest.pt every this many episodes (0: only the final one)."""
    keep_checkpoints: bool = False
    """Also keep checkpoints/episode_<n>.pt for every periodic checkpoint."""
    torch_threads: int = 1
    """Torch intra-op threads per worker (one per worker is fastest on a small CPU)."""
    eval_every: int = -1
    """Evaluate the live policy greedily and sampled from every start cell (up to
    eval_max_starts) every this many episodes, into eval.csv, and once at the end;
    -1: 5 x the number of evaluation starts (rounded up to 10), which keeps evaluation
    near or under 10 % of training time; 0: no evaluation at all."""
    eval_max_starts: int = 100
    """Start cells per periodic evaluation (all of them when there are fewer; a fixed
    seeded sample otherwise)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Loss settings."""

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ConfigError(f"episodes must be >= 1, got {self.episodes}")
        if self.total_steps < 0:
            raise ConfigError(f"total_steps must be >= 0, got {self.total_steps}")
        if self.workers < 0:
            raise ConfigError(f"workers must be >= 0, got {self.workers}")
        if self.t_max < 1:
            raise ConfigError(f"t_max must be >= 1, got {self.t_max}")
        if self.lr <= 0:
            raise ConfigError(f"lr must be positive, got {self.lr}")
        if self.lr_warmup < 0:
            raise ConfigError(f"lr_warmup must be >= 0, got {self.lr_warmup}")
        if self.eval_every < -1:
            raise ConfigError(f"eval_every must be >= -1, got {self.eval_every}")
        if self.eval_max_starts < 1:
            raise ConfigError(f"eval_max_starts must be >= 1, got {self.eval_max_starts}")
        if self.checkpoint_every < 0:
            raise ConfigError(f"checkpoint_every must be >= 0, got {self.checkpoint_every}")


def step_budget_first(values: dict[str, Any], total_steps: Any = None) -> dict[str, Any]:
    """``values`` (a config table being resolved) with ``episodes`` set to
    :data:`NO_EPISODE_LIMIT` when a step budget is asked (``total_steps`` in it, or the
    given ``total_steps``) and no episode budget was: a step budget, when given, is the
    budget, not capped by the default 1000 episodes."""
    steps = values.get("total_steps") if total_steps is None else total_steps
    if steps and "episodes" not in values:
        return {**values, "episodes": NO_EPISODE_LIMIT}
    return values


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-able dict of a (nested) config dataclass."""
    d = dataclasses.asdict(cfg)
    return _jsonable(d)


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def from_dict(cls: type, d: dict[str, Any], where: str | None = None) -> Any:
    """Build ``cls`` from a dict as written by :func:`to_dict` or read from TOML: unknown
    keys and values of the wrong type (``lr = "abc"``) are a ConfigError naming the
    field, checked against the dataclass's own type hints (:mod:`geonav.configcheck`).

    Args:
        cls: a config dataclass.
        d: field name -> value.
        where: how the user names the table (``[a3c]``, ``[stages.pre]``) for messages;
            default the class name.
    """
    from geonav.configcheck import build

    if not isinstance(d, dict):
        raise ConfigError(f"{where or cls.__name__} config must be a mapping, got "
                          f"{type(d).__name__}")
    known = sorted(f.name for f in fields(cls))
    unknown = sorted(set(d) - set(known))
    return build(cls, d, where or cls.__name__,
                 unknown_message=f"unknown {cls.__name__} option(s) {unknown}; known: {known}"
                 if unknown else None)


def field_help(cls: type) -> dict[str, str]:
    """Field name -> its docstring (for argparse help), read from the class source."""
    import ast
    import inspect
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    for node, nxt in zip(body, body[1:], strict=False):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            out[node.target.id] = " ".join(nxt.value.value.split())
    return out
