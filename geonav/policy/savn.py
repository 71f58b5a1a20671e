"""SAVN baseline (ALGORITHMS.md (b); allenai/savn ``runners/savn_train.py``).

The shared parameters are the policy P and the learned interaction loss Lambda (a
temporal conv net, :class:`InteractionLoss`). Per episode (one worker):

1. theta_0 = a leaf copy of P (``sync``);
2. act k steps with theta_m; if done, stop;
3. if m < G (G = -1: no limit): L_int = ||TCN_Lambda(X)||_2 over the segment's rows
   X_t = [h_t, pi_t] (the LSTM output and the action probabilities), and
   theta_{m+1} = theta_m - alpha grad_theta L_int (create_graph, retain_graph);
   Lambda is not adapted;
4. the graph and h are kept over the whole episode (never detached);
5. at the end the meta-loss is L_AC over the whole episode with B = 0; its gradient
   w.r.t. theta_0 (and Lambda, which gets gradient only through the second-order
   path) goes to the shared ``.grad`` and the shared Adam steps.

Acting is under no_grad on a copy of the network loaded with theta_m; each segment is
recomputed in one batched call from the (graph) end state of the previous one. A
previous-view source (curriculum option B, ``prev_view``) feeds the extra input slot as
in ISAR.
"""

from __future__ import annotations

import copy
import time
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from geonav.policy.a3c import A3CTrainer, A3CWorker
from geonav.policy.agent import choose_action, obs_inputs
from geonav.policy.evaluation import spl
from geonav.policy.functional import (
    Segment,
    grads_of,
    load_values,
    segment_forward,
    sgd_step,
    teacher_kl,
)
from geonav.policy.isar import (
    EpisodeTally,
    MetaWorkerMixin,
    check_prev_view,
    gradient_path,
    prev_args,
    teacher_record,
)
from geonav.policy.losses import actor_critic_loss
from geonav.policy.meta_config import SAVNConfig
from geonav.policy.model import ActorCritic


class InteractionLoss(nn.Module):
    """SAVN's learned loss: a causal TCN with the k time steps as channels, convolving
    along the feature axis: k -> ``channels`` (kernel 2, dilation 1), then -> 1 (kernel 2,
    dilation 2), leaky ReLU after each; the loss is the L2 norm of the output.

    Parameter names start with ``ll_`` as in allenai/savn ``models/tcn.py``.
    """

    def __init__(self, k_steps: int, channels: int = 10) -> None:
        super().__init__()
        self.k_steps = k_steps
        self.ll_conv1 = nn.Conv1d(k_steps, channels, 2, padding=1, dilation=1)
        self.ll_conv2 = nn.Conv1d(channels, 1, 2, padding=2, dilation=2)

    def forward(self, rows: torch.Tensor) -> torch.Tensor:
        """rows: (k, F) -> scalar loss. Padding then chomping the right end keeps it causal."""
        if rows.shape[0] != self.k_steps:
            raise ValueError(f"the learned loss needs exactly {self.k_steps} rows, "
                             f"got {rows.shape[0]}")
        x = rows.unsqueeze(0)                                   # (1, k, F)
        x = F.leaky_relu(self.ll_conv1(x)[..., :-1])            # (1, C, F)
        x = F.leaky_relu(self.ll_conv2(x)[..., :-2])            # (1, 1, F)
        return x.pow(2).sum().sqrt()


class SAVNWorker(MetaWorkerMixin, A3CWorker):
    """One SAVN worker (see the module docstring)."""

    cfg: SAVNConfig

    def __init__(self, *args: Any, tcn: InteractionLoss, shared_tcn: InteractionLoss | None =
                 None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.tcn = tcn
        self.names = [n for n, _ in self.model.named_parameters()]
        self.n_policy = len(self._params)
        self._params = self._params + list(tcn.parameters())
        if self._shared_params is not None:
            assert shared_tcn is not None
            self._shared_params = self._shared_params + list(shared_tcn.parameters())
        self.actor_net = copy.deepcopy(self.model).requires_grad_(False)

    @classmethod
    def create(cls, rank: int, shared_model: Any, optimizer: Any, env: Any, net_cfg: Any,
               cfg: Any, frozen: Any, seed: int, extra: dict[str, Any] | None = None
               ) -> A3CWorker:
        shared_tcn = (extra or {})["aux"]["interaction_loss"]
        local = ActorCritic(net_cfg)
        local.load_state_dict(shared_model.state_dict())
        tcn = copy.deepcopy(shared_tcn)
        w = cls(rank, local, optimizer, env, cfg, frozen, seed, shared_model=shared_model,
                tcn=tcn, shared_tcn=shared_tcn)
        w.attach(extra)
        return w

    def run_episode(self, episode: int) -> dict[str, Any]:
        t0 = time.perf_counter()
        cfg = self.cfg
        obs, info = self.reset_env()
        shortest = int(info["shortest_path"])
        lam = self.lam(episode)
        if self.teacher is not None:
            self.teacher.reset(info)
        view, target = obs_inputs(obs, info, self.frozen)
        prev = self.prev_reset(info)
        self.sync()
        policy = self._params[:self.n_policy]
        theta = dict(zip(self.names, policy, strict=True))
        state = self.model.initial_state()
        gstate = state
        all_logits, all_values, actions, rewards, kls = [], [], [], [], []
        m = 0
        tally = EpisodeTally()
        while not (tally.terminated or tally.truncated):
            load_values(self.actor_net, theta)
            with torch.no_grad():
                tfeat = self.actor_net.features(target[None])
            seg = Segment(state, target)
            for _ in range(cfg.k_steps):
                with torch.no_grad():
                    logits, _, state = self.actor_net(view[None, None], tfeat, state,
                                                      *prev_args(prev))
                a = choose_action(logits[0, 0], False, self.rng)
                view, prev, info, ended = self.step_into(seg, a, view, prev, info, tally)
                if ended:
                    break
            t, terminated, truncated = tally.t, tally.terminated, tally.truncated
            logits, values, hs, gstate = segment_forward(
                self.model, theta, torch.stack(seg.views), target, gstate, hidden=True,
                prev=seg.prev())
            all_logits.append(logits)
            all_values.append(values)
            actions += seg.actions
            rewards += seg.rewards
            kl = teacher_kl(torch.stack(seg.teacher_logp), logits) \
                if lam > 0.0 and seg.teacher_logp else None
            if kl is not None:
                kls.append(kl)
            if terminated or truncated:
                break
            if cfg.inner_steps < 0 or m < cfg.inner_steps:
                rows = torch.cat([hs, F.softmax(logits, dim=-1)], dim=-1)   # (k, H + A)
                l_int = self.tcn(rows)
                if kl is not None:
                    l_int = l_int + lam * kl
                theta = sgd_step(theta, l_int, cfg.inner_lr, create_graph=cfg.second_order)
                m += 1
                self._event("inner", t)
        bootstrap = 0.0
        if truncated and not terminated and cfg.loss.bootstrap_on_truncation:
            with torch.no_grad():
                _, v_next, _ = self.actor_net(view[None, None], tfeat, state,
                                              *prev_args(prev))
            bootstrap = float(v_next[0, 0])
        terms = actor_critic_loss(torch.cat(all_logits), torch.cat(all_values), actions,
                                  rewards, bootstrap, cfg.loss)
        meta = terms.total
        if kls:
            meta = meta + lam * torch.stack(kls).sum()
        for p, g in zip(self._params, grads_of(meta, self._params), strict=True):
            p.grad = g
        self.apply_gradients()
        self._event("adapt", t, m)
        self.env_steps += t
        success = bool(info["success"])
        return {"episode": episode, "worker": self.rank, "task": info["task"],
                "task_index": int(info["task_index"]), "return": tally.ret, "length": t,
                "success": success, "spl": spl(success, shortest, t),
                "collisions": tally.collisions, "shortest_path": shortest,
                "policy_loss": terms.policy.item(), "value_loss": terms.value.item(),
                "entropy": terms.entropy.item() / max(t, 1), "env_steps": t,
                "wall_s": time.perf_counter() - t0, "inner_updates": m,
                "adaptive_updates": 1, "kl_weight": lam}


class SAVNTrainer(A3CTrainer):
    """Trains an :class:`ActorCritic` plus its learned loss with SAVN (arguments as
    :class:`A3CTrainer`, with a :class:`SAVNConfig`). Checkpoints hold the policy under
    ``model`` and the learned loss under ``extra['interaction_loss']``."""

    algorithm = "savn"
    config_key = "savn"
    worker_cls = SAVNWorker

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: SAVNConfig | None = None,
                 *, teacher: Any = None, prev_view: Any = None, **kwargs: Any) -> None:
        self.teacher_spec = teacher
        self.prev_view_spec = prev_view
        super().__init__(env_factory, net_cfg, cfg if cfg is not None else SAVNConfig(),
                         **kwargs)
        check_prev_view(self.net_cfg, prev_view)

    def build_aux(self) -> dict[str, nn.Module]:
        return {"interaction_loss": InteractionLoss(self.cfg.k_steps,  # type: ignore[attr-defined]
                                                    self.cfg.tcn_channels)}  # type: ignore

    def worker_extra(self) -> dict[str, Any] | None:
        extra = dict(super().worker_extra() or {})
        if self.teacher_spec is not None:
            extra["teacher"] = self.teacher_spec
        if self.prev_view_spec is not None:
            extra["prev_view"] = self.prev_view_spec
        return extra

    def inline_worker(self) -> A3CWorker:
        w = SAVNWorker(0, self.model, self.optimizer, self.env, self.cfg, self.frozen,
                       self.cfg.seed, rng_state=self.rng_state,
                       tcn=self.aux["interaction_loss"])  # type: ignore[arg-type]
        w.attach(self.worker_extra())
        return w

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["gradient_path"] = {**gradient_path(self.cfg), "path": "recompute"}
        d["teacher"] = teacher_record(self.teacher_spec, self.prev_view_spec)
        return d


def train_savn(env_factory: Any, net_cfg: Any = None, cfg: SAVNConfig | None = None,
               **kwargs: Any) -> Any:
    """Build a :class:`SAVNTrainer` and run it."""
    return SAVNTrainer(env_factory, net_cfg, cfg, **kwargs).train()
