"""ISAR, Algorithm 1 of the paper as resolved in ALGORITHMS.md (c).

Objects: the adaptive policy phi is global (the trainer's shared model, SharedAdam
with lr beta = ``cfg.lr``); the interaction policy theta is a name -> tensor dict per
episode. Per episode (one worker):

1. phi_hat = the local leaf copy of the global phi (``sync``); theta = phi_hat; h = 0.
2. For t = 1..T_max act with theta; at a segment end (t mod N = 0, or done):
   append L_AC(theta; S) (+ lambda KL to the curriculum teacher) to the window;
   if the window holds fewer than K losses and the episode goes on:
   theta <- theta - alpha grad_theta L (create_graph = second_order);
   otherwise: grad_phi_hat of the window's sum into the global phi's ``.grad``
   (clip), Adam step, phi_hat <- the new phi, theta <- phi_hat, detach h and the
   previous-action input, empty the window (a partial window is flushed at done).

Gradient path (``cfg.gradient_path``): 'recompute' acts under no_grad on a plain copy
of the network loaded with theta and recomputes each segment in one batched call from
its start state, carrying the recomputed (graph) end state into the next segment of
the window: the same numbers and the same graph as 'per-step', which keeps the graph
of every acting forward.

With a previous-view source (the curriculum's option B, ``prev_view``), every step's
network call also gets the view at the current cell at the previous altitude in the
extra input slot (stored per segment for the recompute); without one the slot, if the
network has it, is zero-filled.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Any

import torch

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer, A3CWorker
from geonav.policy.agent import choose_action, obs_inputs
from geonav.policy.evaluation import spl
from geonav.policy.functional import (
    Segment,
    grads_of,
    load_values,
    segment_loss,
    sgd_step,
    teacher_kl,
)
from geonav.policy.losses import actor_critic_loss
from geonav.policy.meta_config import PPO_BASE_ASYNC, ISARConfig, check_a3c_base
from geonav.policy.model import detach_state


def prev_args(prev: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """The extra positional argument of a batch-1, one-step forward: () zero-fills."""
    return () if prev is None else (prev[None, None],)


class MetaWorkerMixin:
    """Teacher (curriculum) and instrumentation plumbing shared by SAVN and ISAR workers."""

    teacher: Any = None
    teacher_spec: Any = None
    prev_view: Any = None
    """A :class:`geonav.policy.teacher.PrevViewSource` (option B) or None (zero-filled)."""
    prev_view_spec: Any = None
    events: list[tuple[Any, ...]] | None = None
    """When a list, every inner ('inner', t) and adaptive/meta ('adapt', t, n) update is
    appended (tests)."""

    def attach(self, extra: dict[str, Any] | None) -> None:
        spec = (extra or {}).get("teacher")
        self.teacher_spec = spec
        self.teacher = spec.build() if spec is not None else None
        pspec = (extra or {}).get("prev_view")
        if pspec is not None and not self.model.cfg.prev_view_input:  # type: ignore[attr-defined]
            raise ConfigError("a previous-altitude view source needs a network with the extra "
                              "input slot (NetConfig.prev_view_input = true)")
        self.prev_view_spec = pspec
        self.prev_view = pspec.build(self.frozen) if pspec is not None else None  # type: ignore

    def prev_reset(self, info: dict[str, Any]) -> torch.Tensor | None:
        """New episode: the previous-altitude view at the start cell (None: zero-filled)."""
        if self.prev_view is None:
            return None
        self.prev_view.reset(info)
        return self.prev_view.view(info)

    def prev_at(self, info: dict[str, Any]) -> torch.Tensor | None:
        return self.prev_view.view(info) if self.prev_view is not None else None

    def lam(self, episode: int) -> float:
        return self.teacher_spec.weight(episode) if self.teacher is not None else 0.0

    def _event(self, *e: Any) -> None:
        if self.events is not None:
            self.events.append(e)

    def step_into(self, seg: Segment, a: int, view: torch.Tensor, prev: torch.Tensor | None,
                  info: dict[str, Any], tally: EpisodeTally
                  ) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, Any], bool]:
        """Take action ``a`` from the current ``view`` (SAVN's and ISAR's acting step): the
        teacher's log-probabilities at the cell, the step itself recorded in ``seg`` and
        ``tally``; returns the next view, previous-altitude view, info and whether the
        episode ended."""
        if self.teacher is not None:
            seg.teacher_logp.append(self.teacher.step(info))
        obs, r, terminated, truncated, info = self.env.step(a)  # type: ignore[attr-defined]
        seg.views.append(view)
        if prev is not None:
            seg.prev_views.append(prev)
        seg.actions.append(a)
        seg.rewards.append(float(r))
        tally.ret += float(r)
        tally.collisions += int(bool(info["collided"]))
        tally.t += 1
        tally.terminated, tally.truncated = bool(terminated), bool(truncated)
        view, _ = obs_inputs(obs, info, self.frozen)  # type: ignore[attr-defined]
        return view, self.prev_at(info), info, tally.terminated or tally.truncated


@dataclass
class EpisodeTally:
    """An episode's running totals in the SAVN/ISAR workers' loops."""

    ret: float = 0.0
    collisions: int = 0
    t: int = 0
    terminated: bool = False
    truncated: bool = False


class ISARWorker(MetaWorkerMixin, A3CWorker):
    """One ISAR worker (see the module docstring)."""

    cfg: ISARConfig

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.names = [n for n, _ in self.model.named_parameters()]
        self.actor_net = copy.deepcopy(self.model).requires_grad_(False)
        self.theta_log: list[dict[str, torch.Tensor]] | None = None
        """When a list, theta's values right after each adaptive update (tests)."""

    @classmethod
    def create(cls, rank: int, shared_model: Any, optimizer: Any, env: Any, net_cfg: Any,
               cfg: Any, frozen: Any, seed: int, extra: dict[str, Any] | None = None
               ) -> A3CWorker:
        w = super().create(rank, shared_model, optimizer, env, net_cfg, cfg, frozen, seed, extra)
        w.attach(extra)  # type: ignore[attr-defined]
        return w

    def next_value(self, theta: dict[str, torch.Tensor], view: torch.Tensor,
                   target: torch.Tensor | None, tfeat: Any, state: Any,
                   prev: torch.Tensor | None) -> float:
        """V(s_next) under theta, detached, without advancing the state: per-step path
        (``target`` given) through functional_call, else the loaded actor net."""
        with torch.no_grad():
            if target is not None:
                _, v_next, _ = torch.func.functional_call(
                    self.model, theta, (view[None, None], target[None], detach_state(state),
                                        *prev_args(prev)))
            else:
                _, v_next, _ = self.actor_net(view[None, None], tfeat, state, *prev_args(prev))
        return float(v_next[0, 0])

    def run_episode(self, episode: int) -> dict[str, Any]:
        t0 = time.perf_counter()
        cfg = self.cfg
        per_step = cfg.gradient_path == "per-step"
        obs, info = self.reset_env()
        shortest = int(info["shortest_path"])
        lam = self.lam(episode)
        if self.teacher is not None:
            self.teacher.reset(info)
        view, target = obs_inputs(obs, info, self.frozen)
        prev = self.prev_reset(info)
        self.sync()
        phi = self._params
        theta = dict(zip(self.names, phi, strict=True))
        state = self.model.initial_state()
        gstate = state
        window: list[torch.Tensor] = []
        tally = EpisodeTally()
        tfeat: Any = None
        pl = vl = ent = 0.0
        n_seg = n_inner = n_adapt = 0
        while not (tally.terminated or tally.truncated):
            if not per_step:
                load_values(self.actor_net, theta)
                with torch.no_grad():
                    tfeat = self.actor_net.features(target[None])
            seg = Segment(detach_state(state), target)
            logits_steps, values_steps = [], []
            for _ in range(cfg.n_steps):
                if per_step:
                    logits, v, state = torch.func.functional_call(
                        self.model, theta, (view[None, None], target[None], state,
                                            *prev_args(prev)), strict=True)
                    logits_steps.append(logits[0, 0])
                    values_steps.append(v[0, 0])
                    a = choose_action(logits[0, 0].detach(), False, self.rng)
                else:
                    with torch.no_grad():
                        logits, _, state = self.actor_net(view[None, None], tfeat, state,
                                                          *prev_args(prev))
                    a = choose_action(logits[0, 0], False, self.rng)
                view, prev, info, ended = self.step_into(seg, a, view, prev, info, tally)
                if ended:
                    break
            t, terminated, truncated = tally.t, tally.terminated, tally.truncated
            done = terminated or truncated
            bootstrap = 0.0 if terminated or (truncated and not cfg.loss.bootstrap_on_truncation) \
                else self.next_value(theta, view, target if per_step else None, tfeat, state,
                                     prev)
            if per_step:
                lg = torch.stack(logits_steps)
                terms = actor_critic_loss(lg, torch.stack(values_steps), seg.actions,
                                          seg.rewards, bootstrap, cfg.loss)
                loss = terms.total
                if lam > 0.0 and seg.teacher_logp:
                    loss = loss + lam * teacher_kl(torch.stack(seg.teacher_logp), lg)
            else:
                out = segment_loss(self.model, theta, seg, bootstrap, cfg.loss, gstate,
                                   kl_weight=lam)
                loss, terms, gstate = out.loss, out.terms, out.end_state
            n_seg += 1
            pl += terms.policy.item()
            vl += terms.value.item()
            ent += terms.entropy.item() / len(seg)
            window.append(loss)
            if len(window) < cfg.k_segments and not done:
                theta = sgd_step(theta, loss, cfg.alpha, create_graph=cfg.second_order)
                n_inner += 1
                self._event("inner", t)
            elif done and not cfg.flush_partial_window and len(window) < cfg.k_segments:
                window = []
            else:
                for p, g in zip(phi, grads_of(torch.stack(window).sum(), phi), strict=True):
                    p.grad = g
                self.apply_gradients()
                self.sync()  # phi_hat <- the new global phi; theta <- phi_hat
                theta = dict(zip(self.names, phi, strict=True))
                n_adapt += 1
                self._event("adapt", t, len(window))
                if self.theta_log is not None:
                    self.theta_log.append({n: v.detach().clone() for n, v in theta.items()})
                state = detach_state(state)
                gstate = state
                window = []
        t = tally.t
        self.env_steps += t
        success = bool(info["success"])
        return {"episode": episode, "worker": self.rank, "task": info["task"],
                "task_index": int(info["task_index"]), "return": tally.ret, "length": t,
                "success": success, "spl": spl(success, shortest, t),
                "collisions": tally.collisions, "shortest_path": shortest,
                "policy_loss": pl / max(n_seg, 1), "value_loss": vl / max(n_seg, 1),
                "entropy": ent / max(n_seg, 1), "env_steps": t,
                "wall_s": time.perf_counter() - t0, "inner_updates": n_inner,
                "adaptive_updates": n_adapt, "kl_weight": lam}


def check_prev_view(net_cfg: Any, prev_view: Any) -> None:
    """Refuse a previous-view source for a network without the extra input slot."""
    if prev_view is not None and not net_cfg.prev_view_input:
        raise ConfigError("the previous-altitude view input (curriculum teacher='input') needs "
                          "a network with the extra input slot: NetConfig.prev_view_input = "
                          "true (geonav train/meta-train --prev-view-input)")


def teacher_record(teacher_spec: Any, prev_view_spec: Any) -> dict[str, Any] | None:
    """What config.json records about the curriculum teacher of a stage (A or B)."""
    if prev_view_spec is not None:
        return {"kind": "input", "prev_alt_m": float(prev_view_spec.alt_m)}
    if teacher_spec is not None:
        rec = {"kind": "kl", "checkpoint": str(teacher_spec.checkpoint),
               "budget": teacher_spec.budget, "fraction": teacher_spec.fraction}
        if not teacher_spec.is_paper:
            rec.update(weight=teacher_spec.weight0, schedule=teacher_spec.schedule,
                       loss=teacher_spec.loss, agree=teacher_spec.agree,
                       mask=teacher_spec.mask)
        return rec
    return None


def gradient_path(cfg: Any) -> dict[str, Any]:
    """What config.json records about how gradients were computed."""
    return {"path": getattr(cfg, "gradient_path", "recompute"),
            "order": "second" if getattr(cfg, "second_order", False) else "first",
            "fused_adam": bool(cfg.fused),
            "inner_updates": "torch.func.functional_call + autograd.grad(create_graph="
                             f"{bool(getattr(cfg, 'second_order', False))}, retain_graph=True)"}


class ISARTrainer(A3CTrainer):
    """Trains an :class:`ActorCritic` with ISAR (arguments as :class:`A3CTrainer`, with an
    :class:`ISARConfig`; ``teacher`` adds the curriculum's KL prior)."""

    algorithm = "isar"
    config_key = "isar"
    worker_cls = ISARWorker

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: ISARConfig | None = None,
                 *, teacher: Any = None, prev_view: Any = None, **kwargs: Any) -> None:
        self.teacher_spec = teacher
        self.prev_view_spec = prev_view
        check_a3c_base(cfg, PPO_BASE_ASYNC)
        super().__init__(env_factory, net_cfg, cfg if cfg is not None else ISARConfig(),
                         **kwargs)
        check_prev_view(self.net_cfg, prev_view)

    def worker_extra(self) -> dict[str, Any] | None:
        extra = dict(super().worker_extra() or {})
        if self.teacher_spec is not None:
            extra["teacher"] = self.teacher_spec
        if self.prev_view_spec is not None:
            extra["prev_view"] = self.prev_view_spec
        return extra or None

    def inline_worker(self) -> A3CWorker:
        w = super().inline_worker()
        w.attach(self.worker_extra())  # type: ignore[attr-defined]
        return w

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["gradient_path"] = gradient_path(self.cfg)
        d["teacher"] = teacher_record(self.teacher_spec, self.prev_view_spec)
        return d


def train_isar(env_factory: Any, net_cfg: Any = None, cfg: ISARConfig | None = None,
               **kwargs: Any) -> Any:
    """Build an :class:`ISARTrainer` and run it."""
    return ISARTrainer(env_factory, net_cfg, cfg, **kwargs).train()
