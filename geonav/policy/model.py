"""The actor-critic network f of ALGORITHMS.md 4.0.

Current view and target view -> encoder -> linear to ``embed_dim`` each (ReLU);
previous action probabilities -> linear to ``action_embed_dim`` (ReLU);
concatenate -> fully connected (ReLU) -> LSTMCell -> actor (``n_actions``) and
critic (1) heads (the initialisation and input scaling are ``NetConfig.init``,
``input_norm`` and ``actor_init_std``; why, in docs/learning.md). With
``NetConfig.prev_view_input`` an extra slot E(o^prev)
(ALGORITHMS.md (e), option B) adds the encoder features of the view at the same cell
at the previous curriculum altitude, linear to ``embed_dim`` (ReLU), concatenated after
the target embedding; ``forward``'s ``prev`` argument feeds it, and None zero-fills the
slot's *features* (so the embedding is ReLU(bias)). SAVN's initialisation
(allenai/savn ``models/model_io.py``, ``utils/net_util.py``): Xavier-uniform weights
and zero biases, actor weights column-normalised to std 0.01, critic to 1.0, is kept as
``NetConfig(init='savn')``; the default is orthogonal with ReLU gain and an actor of 1.0.

The recurrent state is a tuple ``(h, c, p)``: LSTM hidden and cell ``(B, lstm_size)``
and the previous action probabilities ``(B, n_actions)`` (zeros at episode start).

``forward`` always takes a sequence: ``obs`` is ``(T, B, ...)``, the target
``(B, ...)`` (constant over an episode). Acting calls it with T = 1; the loss
recomputes a whole rollout with one call from the stored start state. The
previous-action input of step t > 0 is the softmax of step t-1's logits,
computed inside, so T calls with T = 1 and one call with T steps give the same
numbers and the same graph. It is a plain ``nn.Module``, so
``torch.func.functional_call(model, params, (obs, target, state))`` runs it from a
name -> tensor dict (SAVN/ISAR inner updates).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from geonav.errors import ConfigError
from geonav.policy.config import NetConfig
from geonav.policy.encoders import SmallCNN, feature_dim

State = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def norm_col_init(weight: torch.Tensor, std: float, generator: torch.Generator | None = None
                  ) -> None:
    """SAVN's ``norm_col_init``: Gaussian rows rescaled to L2 norm ``std`` (in place)."""
    with torch.no_grad():
        x = torch.randn(weight.shape, generator=generator)
        x *= std / torch.sqrt(x.pow(2).sum(1, keepdim=True))
        weight.copy_(x)


def _xavier_(m: nn.Module) -> None:
    if isinstance(m, (nn.Linear, nn.Conv2d)):
        fan_in = m.weight[0].numel()
        fan_out = m.weight.shape[0] * (m.weight[0, 0].numel() if m.weight.dim() > 2 else 1)
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        with torch.no_grad():
            m.weight.uniform_(-bound, bound)
            if m.bias is not None:
                m.bias.zero_()


INIT_RESETS = ("none", "critic", "heads")
"""What a fine-tune draws again after loading its starting weights (:meth:`ActorCritic.
reset_heads`)."""


class ActorCritic(nn.Module):
    """Actor-critic with an LSTM core (see the module docstring).

    Args:
        cfg: the architecture. With ``encoder='cnn'`` the network owns a trainable
            :class:`SmallCNN` and takes uint8 images; otherwise it takes features
            ``(..., F)`` from a frozen encoder.
    """

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder: SmallCNN | None = SmallCNN(cfg.obs_size_px, cfg.input_norm, cfg.cnn) \
            if cfg.encoder == "cnn" else None
        fdim = feature_dim(cfg)
        self.obs_embed = nn.Linear(fdim, cfg.embed_dim)
        self.target_embed = nn.Linear(fdim, cfg.embed_dim)
        # Only registered when on: without it, parameter names and shapes are the original ones.
        self.prev_embed: nn.Linear | None = nn.Linear(fdim, cfg.embed_dim) \
            if cfg.prev_view_input else None
        # Feed-forward (recurrent=False): no previous-action input and no LSTM.
        self.action_embed: nn.Linear | None = nn.Linear(cfg.n_actions, cfg.action_embed_dim) \
            if cfg.recurrent else None
        # separate_critic: one layer of 2H outputs, the actor's H then the critic's H.
        self.fc = nn.Linear(self.n_view_slots * cfg.embed_dim
                            + (cfg.action_embed_dim if cfg.recurrent else 0),
                            cfg.hidden_size * (2 if cfg.separate_critic else 1))
        self.lstm: nn.LSTMCell | None = nn.LSTMCell(cfg.hidden_size, cfg.lstm_size) \
            if cfg.recurrent else None
        head_in = cfg.lstm_size if cfg.recurrent else cfg.hidden_size
        self.actor = nn.Linear(head_in, cfg.n_actions)
        self.critic = nn.Linear(head_in, 1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """``NetConfig.init`` (draws from torch's global RNG): 'orthogonal' or SAVN's."""
        if self.cfg.init == "savn":
            self.apply(_xavier_)
        else:  # orthogonal, ReLU gain: activations keep their scale through the trunk
            for m in self.modules():
                if isinstance(m, (nn.Linear, nn.Conv2d)):
                    nn.init.orthogonal_(m.weight, math.sqrt(2.0))
                    nn.init.zeros_(m.bias)  # type: ignore[arg-type]
            if self.lstm is not None:
                nn.init.orthogonal_(self.lstm.weight_ih)
                nn.init.orthogonal_(self.lstm.weight_hh)
        if self.lstm is not None:
            with torch.no_grad():
                self.lstm.bias_ih.zero_()
                self.lstm.bias_hh.zero_()
        self.reset_heads("heads")

    def reset_heads(self, which: str) -> None:
        """Draw the output layers again, as :meth:`reset_parameters` does (global RNG), for a
        fine-tune whose starting policy was trained on other returns: 'critic' (the value
        head) or 'heads' (the value and policy heads); 'none' keeps them."""
        if which not in INIT_RESETS:
            raise ConfigError(f"init_reset must be one of {INIT_RESETS}, not {which!r}")
        if which == "none":
            return
        if which == "heads":  # the actor first: reset_parameters' order of draws
            actor_std = self.cfg.actor_init_std
            if actor_std is None:
                actor_std = 0.01 if self.cfg.init == "savn" else 1.0
            norm_col_init(self.actor.weight, actor_std)
        norm_col_init(self.critic.weight, 1.0)
        with torch.no_grad():
            self.critic.bias.zero_()
            if which == "heads":
                self.actor.bias.zero_()

    @property
    def n_view_slots(self) -> int:
        """Image inputs concatenated before the FC layer: current, target (, previous)."""
        return 3 if self.cfg.prev_view_input else 2

    @property
    def takes_images(self) -> bool:
        """True when inputs are uint8 images (trainable CNN), False for features."""
        return self.encoder is not None

    def initial_state(self, batch: int = 1) -> State:
        """Zero LSTM state and zero previous action probabilities."""
        z = torch.zeros(batch, self.cfg.lstm_size)
        return (z, z.clone(), torch.zeros(batch, self.cfg.n_actions))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Views to encoder features: (M, N, N, 3) uint8 -> (M, F); float (M, F) passes through.

        Acting can encode the episode's target once and pass the features to ``forward``.
        """
        if self.encoder is not None and x.dtype == torch.uint8:
            return self.encoder(x)
        return x

    def forward(self, obs: torch.Tensor, target: torch.Tensor, state: State,
                prev: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, State]:
        """Run T steps.

        Args:
            obs: current views, (T, B, N, N, 3) uint8 or (T, B, F) features.
            target: the target view, (B, N, N, 3) uint8 or (B, F) features (frozen encoder,
                or the trainable CNN's output from :meth:`features`).
            state: ``(h, c, p)`` before the first step.
            prev: the previous-altitude views at the same cells, shaped like ``obs``
                (only with ``prev_view_input``); None zero-fills the slot's features.

        Returns:
            logits (T, B, n_actions), values (T, B) and the state after step T, whose
            ``p`` is the softmax of the last logits.
        """
        # Batched mirror: geonav/policy/batched/core.py; change both (test_batched_core.py).
        T, B = obs.shape[0], obs.shape[1]
        obs_f = self.features(obs.reshape(T * B, *obs.shape[2:]))
        tgt_f = self.features(target)
        obs_e = F.relu(self.obs_embed(obs_f)).view(T, B, -1)            # (T, B, E)
        tgt_e = F.relu(self.target_embed(tgt_f)).unsqueeze(0).expand(T, B, -1)
        parts = [obs_e, tgt_e]
        if self.prev_embed is not None:
            if prev is None:  # zero-filled slot
                prev_f = obs_f.new_zeros(obs_f.shape)
            else:
                if prev.shape[:2] != (T, B):
                    raise ValueError(f"prev must be shaped like obs (T={T}, B={B}, ...), got "
                                     f"{tuple(prev.shape)}")
                prev_f = self.features(prev.reshape(T * B, *prev.shape[2:]))
            parts.append(F.relu(self.prev_embed(prev_f)).view(T, B, -1))
        elif prev is not None:
            raise ValueError("this network has no previous-view slot (NetConfig."
                             "prev_view_input=False); do not pass prev")
        # fc(cat(obs_e, tgt_e[, prev_e], act_e)) split by columns: the image part is batched.
        w = self.fc.weight
        k = len(parts) * self.cfg.embed_dim
        pre = F.linear(torch.cat(parts, dim=-1), w[:, :k], self.fc.bias)  # (T, B, H)
        h, c, p = state
        if self.lstm is None:  # feed-forward: the heads read the FC layer's output
            x_pi, x_v = head_inputs(F.relu(pre), self.cfg.hidden_size)
            logits = self.actor(x_pi)
            return logits, self.critic(x_v).squeeze(-1), (h, c, F.softmax(logits[-1], dim=-1))
        assert self.action_embed is not None
        w_act = w[:, k:]  # sliced once: one SliceBackward per call, not one per step
        hs = []
        logits_steps = []
        for t in range(T):
            act_e = F.relu(self.action_embed(p))
            x = F.relu(pre[t] + F.linear(act_e, w_act))
            h, c = self.lstm(x, (h, c))
            logit = self.actor(h)
            p = F.softmax(logit, dim=-1)
            hs.append(h)
            logits_steps.append(logit)
        logits = torch.stack(logits_steps)
        values = self.critic(torch.stack(hs)).squeeze(-1)
        return logits, values, (h, c, p)


def head_inputs(x: torch.Tensor, hidden: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The actor's and the critic's inputs from a feed-forward FC layer's output: the same
    tensor, or its two halves with ``NetConfig.separate_critic`` (2 x ``hidden`` wide)."""
    if x.shape[-1] == hidden:
        return x, x
    return x[..., :hidden], x[..., hidden:]


def detach_state(state: State) -> State:
    """Cut the graph at a rollout boundary (A3C step 5; ISAR after an adaptive update)."""
    return (state[0].detach(), state[1].detach(), state[2].detach())


def param_dict(model: nn.Module) -> dict[str, torch.Tensor]:
    """Name -> parameter, for ``torch.func.functional_call``."""
    return dict(model.named_parameters())


def arch_meta(cfg: NetConfig) -> dict[str, Any]:
    """The JSON-able architecture record written into checkpoints."""
    from geonav.policy.config import to_dict

    return {"class": "ActorCritic", **to_dict(cfg)}
