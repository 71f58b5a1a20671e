"""The batched forward of :class:`~geonav.policy.model.ActorCritic`, with per-slot weights.

This is the one batched mirror of ``ActorCritic.forward``: a change there must be made
here too (``tests/test_batched_core.py`` compares the two in float64 to 1e-10 and fails
otherwise). It runs from a name -> tensor dict of the same parameters (the module's own,
or ISAR's phi), for B slots that may be on different tasks and at different steps of
their episodes:

* views are rows of a table (the frozen encoder's features of every view, or the
  trainable CNN's features of the distinct views of an update, encoded once), selected by
  index per step and slot;
* ``starts`` (T, B) zero a slot's recurrent state before the first step of a new
  episode, so a rollout may cross episode ends (synchronous A2C form);
* per-slot adapted weights are exact and factored (``shared/notes/batched-training.md``):
  the inner SGD update of a linear layer y = W x + b over a segment is a sum of
  rank-one terms u v^T (u = dL/dy, v = x), so slot s's weights are
  ``W_s = W + sum_r U[s, r] V[s, r]^T`` and ``b_s = b + db[s]`` with U = -alpha u;
  ``W_s x = W x + U^T (V x)`` keeps one shared matrix product per layer. The LSTM's
  input and hidden matrices are two such layers sharing u = dL/dgates. Kept in the graph
  (create_graph) the factors give the exact second-order gradient.
* the trainable CNN's per-slot adapted weights are dense (:class:`SlotDeltas`,
  ``theta_s = phi + delta[s]``): a convolution's weight gradient sums an outer product
  over every output position of every view, so its factors would outnumber its weights
  (11k values at 84 px). :func:`encode_slots` encodes each slot's views with its own
  weights (``torch.func.vmap`` over ``functional_call`` of the module's own encoder, a
  grouped convolution), and the :class:`Recorder` takes the per-slot gradients w.r.t.
  those (B, ...) weight tensors together with the linear layers' output gradients.

Layer order and maths as ActorCritic.forward: embeddings with ReLU, the FC layer over
``cat(obs_e, tgt_e, act_e)`` with ReLU, an LSTM cell (gates i, f, g, o as
``nn.LSTMCell``), actor and critic heads, the previous action probabilities
``p = softmax(logits)`` fed back.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch.nn import functional as F

from geonav.errors import ConfigError
from geonav.policy.model import ActorCritic, State, head_inputs

Params = dict[str, torch.Tensor]

#: layer key -> (weight name, bias name) of the linear maps that per-slot factors adapt.
LAYERS: dict[str, tuple[str, str]] = {
    "obs_embed": ("obs_embed.weight", "obs_embed.bias"),
    "target_embed": ("target_embed.weight", "target_embed.bias"),
    "prev_embed": ("prev_embed.weight", "prev_embed.bias"),
    "action_embed": ("action_embed.weight", "action_embed.bias"),
    "fc": ("fc.weight", "fc.bias"),
    "lstm_ih": ("lstm.weight_ih", "lstm.bias_ih"),
    "lstm_hh": ("lstm.weight_hh", "lstm.bias_hh"),
    "actor": ("actor.weight", "actor.bias"),
    "critic": ("critic.weight", "critic.bias"),
}


def check_supported(model: ActorCritic, *, per_slot_parameters: bool = False) -> None:
    """Refuse what the batched forward does not implement (typed, actionable errors):
    stacked per-slot parameters (meta-training's phi^i) need a frozen encoder."""
    if per_slot_parameters and model.encoder is not None:
        raise ConfigError("per-task parameters on the batched engine (meta-training with the "
                          "ISAR or A3C base) need a frozen encoder (encoder = 'random' or "
                          "'resnet18'); the trainable CNN runs on engine = 'async'")


@dataclass
class Factors:
    """Per-slot rank-one updates of one linear layer (see the module docstring).

    For the view embeddings, whose inputs are rows of a constant feature table, the
    inputs may be kept as row indices (``V_idx``) with the table's Gram matrix: then
    ``V x`` is a lookup ``gram[V_idx, x_idx]`` instead of a (B, R, F) product.
    """

    U: torch.Tensor | None = None
    """(B, R, out): -alpha times the output gradients."""
    V: torch.Tensor | None = None
    """(B, R, in): the layer inputs (or None with ``V_idx``)."""
    db: torch.Tensor | None = None
    """(B, out): bias change."""
    V_idx: torch.Tensor | None = None
    """(B, R) table rows of the inputs (with ``gram``)."""
    gram: torch.Tensor | None = None
    """(C, C) table @ table.T of the constant feature table the rows index."""

    def correction(self, x: torch.Tensor, idx: torch.Tensor | None = None
                   ) -> torch.Tensor | None:
        """(B, in) -> (B, out): (W_s - W) x + (b_s - b), or None when empty (``idx``: the
        table rows of x, for factors kept as row indices)."""
        out = self.db
        if self.U is not None:  # row-vector products: 2-8x faster than (B, R, in) @ x
            if self.V_idx is not None:
                assert self.gram is not None and idx is not None
                vx = self.gram[self.V_idx, idx.unsqueeze(1)].unsqueeze(1)   # (B, 1, R)
            else:
                assert self.V is not None
                vx = torch.bmm(x.unsqueeze(1), self.V.transpose(1, 2))      # (B, 1, R)
            uvx = torch.bmm(vx, self.U).squeeze(1)                          # (B, out)
            out = uvx if out is None else out + uvx
        return out

    def add(self, u: torch.Tensor, v: torch.Tensor, lr: float,
            v_idx: torch.Tensor | None = None, gram: torch.Tensor | None = None) -> Factors:
        """These factors plus the SGD step -lr * sum_r u_r v_r^T: u (B, R, out), v (B, R, in)
        (or its table rows ``v_idx`` (B, R) with the table's ``gram``)."""
        U = -lr * u
        db = U.sum(1)
        if v_idx is not None:
            return Factors(U if self.U is None else torch.cat([self.U, U], 1), None,
                           db if self.db is None else self.db + db,
                           v_idx if self.V_idx is None else torch.cat([self.V_idx, v_idx], 1),
                           gram)
        return Factors(U if self.U is None else torch.cat([self.U, U], 1),
                       v if self.V is None else torch.cat([self.V, v], 1),
                       db if self.db is None else self.db + db)

    def cleared(self, keep: torch.Tensor) -> Factors:
        """W_s <- W, b_s <- b where ``keep`` (B,) is 0 (those slots' factors zeroed)."""
        k = keep.view(-1, 1)
        return replace(self, U=None if self.U is None else self.U * k.unsqueeze(-1),
                       db=None if self.db is None else self.db * k)

    def dense(self, table: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, out, in) weight change and (B, out) bias change (tests; ``table`` resolves
        row-index factors)."""
        assert self.U is not None and self.db is not None
        V = self.V if self.V_idx is None else table[self.V_idx]  # type: ignore[index]
        assert V is not None
        return torch.bmm(self.U.transpose(1, 2), V), self.db


ENCODER = "encoder"
"""The :data:`Adapted` key of the trainable CNN's per-slot weights (:class:`SlotDeltas`)."""


@dataclass
class SlotDeltas:
    """Per-slot adapted weights of the trainable CNN, dense: theta_s = phi + delta[name][s]."""

    delta: dict[str, torch.Tensor]
    """Encoder parameter name (without ``encoder.``) -> (B, ...) weight change."""

    def add(self, grads: dict[str, torch.Tensor], lr: float) -> SlotDeltas:
        """These changes plus the SGD step -lr * grads (name -> (B, ...))."""
        return SlotDeltas({n: -lr * g if n not in self.delta else self.delta[n] - lr * g
                           for n, g in grads.items()})

    def cleared(self, keep: torch.Tensor) -> SlotDeltas:
        """theta_s <- phi where ``keep`` (B,) is 0."""
        return SlotDeltas({n: d * keep.view(-1, *([1] * (d.dim() - 1)))
                           for n, d in self.delta.items()})


Adapted = dict[str, Any]
"""Layer key -> :class:`Factors`, and :data:`ENCODER` -> :class:`SlotDeltas`."""


def encoder_weights(params: Params, adapted: Adapted | None, b: int) -> Params:
    """The trainable CNN's weights of every slot, name (without ``encoder.``) -> (B, ...):
    phi expanded, plus the slots' :class:`SlotDeltas` when adapted. Packed runs'
    (:class:`RunParams`, (R, ...) each): run r's weights for its B / R slots."""
    d = (adapted or {}).get(ENCODER)
    out: Params = {}
    for name, p in params.items():
        if name.startswith("encoder."):
            key = name[len("encoder."):]
            w = p.repeat_interleave(b // p.shape[0], 0) if isinstance(params, RunParams) \
                else p.expand(b, *p.shape)
            out[key] = w if d is None or key not in d.delta else w + d.delta[key]
    return out


def encode_slots(encoder: torch.nn.Module, weights: Params, images: torch.Tensor
                 ) -> torch.Tensor:
    """(B, M, N, N, 3) uint8 views, slot s's M encoded with its weights -> (B, M, F)."""
    return torch.func.vmap(lambda w, x: torch.func.functional_call(encoder, w, (x,)))(
        weights, images)


@dataclass
class Recorder:
    """Collects (layer key, input, output) of every adapted linear map of a segment, so
    that one ``autograd.grad`` of the segment loss w.r.t. the outputs gives the u's."""

    entries: list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor | None]] = field(
        default_factory=list)
    gram: torch.Tensor | None = None
    """The Gram matrix of the feature table, when inputs are recorded as row indices."""
    encoder_uses: list[Params] = field(default_factory=list)
    """The per-slot trainable-CNN weights (:func:`encoder_weights`) of every encoding."""
    back: list[tuple[str, torch.Tensor, torch.Tensor]] = field(default_factory=list)
    """(layer key, g_x, g_y) of every backward product g_x = g_y W_s^T of a per-slot weight
    that an inner step with ``create_graph`` took through a recorded map
    (:class:`SlotProduct`): the second-order path through W_s, see :func:`back_grads`."""

    def add(self, key: str, x: torch.Tensor, y: torch.Tensor,
            idx: torch.Tensor | None = None) -> None:
        self.entries.append((key, x, y, idx))

    def add_encoder(self, weights: Params) -> None:
        if not any(w is weights for w in self.encoder_uses):
            self.encoder_uses.append(weights)

    def inner_factors(self, loss: torch.Tensor, adapted: Adapted, lr: float, *,
                      create_graph: bool, weights: torch.Tensor | None = None) -> Adapted:
        """The adapted weights after theta <- theta - lr * d loss / d theta, per slot.

        ``loss`` must be a sum of per-slot losses (slot s's rows of the outputs then get
        dL_s/dy). ``weights`` (B,) scales each slot's step (0 keeps a slot unchanged).
        ``retain_graph=True`` always: later losses share this graph (ALGORITHMS.md,
        "Differentiable inner updates"), even in first order.
        """
        ys: list[torch.Tensor] = []
        pos: dict[int, int] = {}
        for _, _, y, _ in self.entries:
            if id(y) not in pos:
                pos[id(y)] = len(ys)
                ys.append(y)
        enc = [(n, w) for use in self.encoder_uses for n, w in use.items()]
        grads = torch.autograd.grad(loss, ys + [w for _, w in enc], create_graph=create_graph,
                                    retain_graph=True, allow_unused=True)
        out = dict(adapted)
        if enc:  # the CNN's per-slot gradients: summed over its uses (each is theta_s)
            g_enc: dict[str, torch.Tensor] = {}
            for (n, w), g in zip(enc, grads[len(ys):], strict=True):
                g = torch.zeros_like(w) if g is None else g
                if not create_graph:
                    g = g.detach()
                if weights is not None:
                    g = g * weights.view(-1, *([1] * (g.dim() - 1))).to(g.dtype)
                g_enc[n] = g if n not in g_enc else g_enc[n] + g
            out[ENCODER] = adapted.get(ENCODER, SlotDeltas({})).add(g_enc, lr)
        per_key: dict[str, tuple[list[torch.Tensor], list[torch.Tensor], list[Any]]] = {}
        for key, x, y, idx in self.entries:
            g = grads[pos[id(y)]]
            if g is None:
                g = torch.zeros_like(y)
            if not create_graph:
                g, x = g.detach(), x.detach()
            if weights is not None:
                g = g * weights.view(-1, 1).to(g.dtype)
            us, vs, ids = per_key.setdefault(key, ([], [], []))
            us.append(g)
            vs.append(x)
            ids.append(idx)
        for key, (us, vs, ids) in per_key.items():
            by_index = self.gram is not None and all(i is not None for i in ids)
            out[key] = adapted.get(key, Factors()).add(
                torch.stack(us, 1), None if by_index else torch.stack(vs, 1),  # type: ignore
                lr, torch.stack(ids, 1) if by_index else None, self.gram)
        return out


class AtPsi(dict):  # type: ignore[type-arg]
    """Per-slot parameters phi^s of meta-training while every slot's weights still equal
    psi (before a task's first in-task Adam step): the weights are psi's own (out, in)
    tensors, shared, the biases the slots' (B, out) leaves. Each product is then one
    matrix product over the B rows (:class:`SharedProduct`) instead of B products that
    read B copies of the weights, with the same per-slot gradients from the records."""


class SharedProduct(torch.autograd.Function):
    """y = x W^T for a weight W (out, in) shared by the B rows of x (B, in), with no
    gradient for W: as :class:`SlotProduct` (whose per-slot gradients it gives, from the
    same records), for slots whose weights are all equal."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, w: torch.Tensor, key: str,
                sink: Recorder | None) -> torch.Tensor:
        ctx.save_for_backward(w)
        ctx.key = key
        # a weak reference: the recorder keeps the backward products made with the graph,
        # whose graph holds this node; a strong one would close a cycle through autograd's
        # C++ nodes that Python's collector cannot see, and every window's graph would
        # stay alive (bench/bench_meta_memory.py: about 290 MiB per 1,000 episodes)
        ctx.sink = None if sink is None else weakref.ref(sink)
        return x @ w.t()

    @staticmethod
    def backward(ctx: Any, gy: torch.Tensor) -> tuple[Any, ...]:
        (w,) = ctx.saved_tensors
        gx = SharedProductT.apply(gy, w)
        sink = None if ctx.sink is None else ctx.sink()
        if torch.is_grad_enabled() and gx.requires_grad and sink is not None:
            sink.back.append((ctx.key, gx, gy.detach()))
        return gx, None, None, None


class SharedProductT(torch.autograd.Function):
    """g_x = g_y W, the backward product of :class:`SharedProduct` (no gradient for W)."""

    @staticmethod
    def forward(ctx: Any, gy: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(w)
        return gy @ w

    @staticmethod
    def backward(ctx: Any, ggx: torch.Tensor) -> tuple[Any, ...]:
        (w,) = ctx.saved_tensors
        return ggx @ w.t(), None


class RunParams(dict):  # type: ignore[type-arg]
    """Parameters of packed runs: name -> the R runs' tensors stacked, (R, ...) each
    (:mod:`geonav.policy.batched.packed`); a slot's rows are those of its run."""


def affine(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor | None = None) -> torch.Tensor:
    """x W^T + b. With run-stacked parameters (packed runs: w (R, out, in), b (R, out)) the
    rows of x (R * n, in) are R equal groups in run order, each mapped by its run's W."""
    if w.dim() == 2:
        return F.linear(x, w, b)
    r = w.shape[0]
    y = torch.bmm(x.reshape(r, -1, x.shape[-1]), w.transpose(1, 2))
    if b is not None:
        y = y + b.unsqueeze(1)
    return y.reshape(-1, w.shape[1])


class SlotProduct(torch.autograd.Function):
    """y = x W_s for per-slot weights W (B, in, out) and x (B, in), with no gradient for W.

    W_s enters the loss in two places only: this product, and (an inner step taken with
    ``create_graph``) its backward product g_x = g_y W_s^T. Autograd would give W_s's
    gradient as an outer product per step and use, accumulated one by one (a (B, in, out)
    tensor per step: most of a second-order window's backward). Here W_s has no gradient
    edge at all; its gradient is assembled from the recorded maps instead, in one batched
    product per layer: sum_t x_t^T dL/dy_t (:func:`layer_grads`) plus
    sum_t (dL/dg_x,t)^T g_y,t (:func:`back_grads`, from the ``sink``'s records of the
    backward products made with the graph). Exact: the same terms, summed in another order.
    """

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, w: torch.Tensor, key: str,
                sink: Recorder | None) -> torch.Tensor:
        ctx.save_for_backward(w)
        ctx.key = key
        # a weak reference: the recorder keeps the backward products made with the graph,
        # whose graph holds this node; a strong one would close a cycle through autograd's
        # C++ nodes that Python's collector cannot see, and every window's graph would
        # stay alive (bench/bench_meta_memory.py: about 290 MiB per 1,000 episodes)
        ctx.sink = None if sink is None else weakref.ref(sink)
        return torch.bmm(x.unsqueeze(1), w).squeeze(1)

    @staticmethod
    def backward(ctx: Any, gy: torch.Tensor) -> tuple[Any, ...]:
        (w,) = ctx.saved_tensors
        gx = SlotProductT.apply(gy, w)
        sink = None if ctx.sink is None else ctx.sink()
        if torch.is_grad_enabled() and gx.requires_grad and sink is not None:
            sink.back.append((ctx.key, gx, gy.detach()))  # create_graph: W_s's 2nd path
        return gx, None, None, None


class SlotProductT(torch.autograd.Function):
    """g_x = g_y W_s^T, the backward product of :class:`SlotProduct` (no gradient for W)."""

    @staticmethod
    def forward(ctx: Any, gy: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(w)
        return torch.bmm(gy.unsqueeze(1), w.transpose(1, 2)).squeeze(1)

    @staticmethod
    def backward(ctx: Any, ggx: torch.Tensor) -> tuple[Any, ...]:
        (w,) = ctx.saved_tensors
        return torch.bmm(ggx.unsqueeze(1), w).squeeze(1), None


def back_grads(back: list[tuple[str, torch.Tensor, torch.Tensor]],
               gx_grads: list[torch.Tensor | None]) -> dict[str, torch.Tensor]:
    """The weights' gradients through the recorded backward products g_x = g_y W_s^T
    (:attr:`Recorder.back`; ``gx_grads`` dL/dg_x of each): weight name -> (B, in, out)
    sum_t (dL/dg_x,t)^T g_y,t, one batched product per layer."""
    per_key: dict[str, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
    for (key, _, gy), g in zip(back, gx_grads, strict=True):
        if g is None:
            continue
        ls, gys = per_key.setdefault(key, ([], []))
        ls.append(g)
        gys.append(gy)
    return {LAYERS[key][0]: torch.bmm(torch.stack(ls, 2), torch.stack(gys, 1))
            for key, (ls, gys) in per_key.items()}


def layer_grads(entries: list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor | None]],
                out_grads: dict[int, torch.Tensor | None]) -> dict[str, torch.Tensor]:
    """Per-slot weight and bias gradients of recorded linear maps from their output
    gradients (``out_grads``: id(y) -> dL/dy): dW_s = sum_t u_t x_t^T in one batched
    product per layer, db_s = sum_t u_t; parameter name -> (B, ...) tensor, the weights'
    (B, in, out), transposed as per-slot weights are stored (see :func:`linear`).

    Exact when the weights enter the loss only through the recorded products W x (first
    order, or layers whose inputs are constant)."""
    per_key: dict[str, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}
    for key, x, y, _ in entries:
        g = out_grads.get(id(y))
        us, xs = per_key.setdefault(key, ([], []))
        us.append(torch.zeros_like(y) if g is None else g)
        xs.append(x.detach())
    out: dict[str, torch.Tensor] = {}
    for key, (us, xs) in per_key.items():
        wname, bname = LAYERS[key]
        u = torch.stack(us, 1)                                          # (B, T, out)
        out[wname] = torch.bmm(torch.stack(xs, 2), u)                   # (B, in, out)
        out[bname] = u.sum(1)
    return out


def linear(params: Params, key: str, x: torch.Tensor, adapted: Adapted | None,
           rec: Recorder | None, idx: torch.Tensor | None = None,
           base: torch.Tensor | None = None, back: Recorder | None = None) -> torch.Tensor:
    """y = W_s x + b_s for a (B, in) input, recorded for inner gradients when asked
    (``idx``: x's rows of the constant feature table, for the Gram-matrix factors).

    W and b are shared (out, in) and (out,), or per slot (B, in, out) and (B, out):
    stacked per-task parameters, the weights stored transposed, for which the batched
    product x W_s^T and its weight gradient are 5-10x faster on the CPU than W_s x; their
    gradients come from the records (:class:`SlotProduct`; ``back``: the recorder of the
    backward products when ``rec`` is None, as for the LSTM's hidden matrix). The
    factors apply on top of either. ``base`` (B, out):
    W x + b computed elsewhere (the caller differentiates through it: meta-training
    evaluates its per-slot view embeddings once per window)."""
    wname, bname = LAYERS[key]
    w, b = params[wname], params[bname]
    if base is not None:
        y = base.clone()  # a node per call: the recorder's entries must not share outputs
    elif isinstance(params, AtPsi):  # phi^s = psi for every slot: shared (out, in) weights
        y = SharedProduct.apply(x, w.detach(), key, rec if rec is not None else back) + b
    elif isinstance(params, RunParams):  # packed runs: (R, out, in), run r's rows
        y = affine(x, w, b)
    elif w.dim() == 3:  # per-slot (B, in, out) weights, (B, out) biases: meta-training's phi^i
        y = SlotProduct.apply(x, w.detach(), key, rec if rec is not None else back) + b
    else:
        y = F.linear(x, w, b)
    if adapted is not None and key in adapted:
        corr = adapted[key].correction(x, idx)
        if corr is not None:
            y = y + corr
    if rec is not None:
        rec.add(key, x, y, idx)
    return y


def lstm_cell(gates: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """nn.LSTMCell's state update from its pre-activation gates (i, f, g, o)."""
    i, f, g, o = gates.chunk(4, dim=-1)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c), c


def target_embedding(params: Params, tgt_f: torch.Tensor, adapted: Adapted | None = None,
                     rec: Recorder | None = None, idx: torch.Tensor | None = None,
                     base: torch.Tensor | None = None) -> torch.Tensor:
    """(B, F) target features -> (B, E) embeddings (constant over an episode segment)."""
    return F.relu(linear(params, "target_embed", tgt_f, adapted, rec, idx, base))


def view_slots(params: Params) -> int:
    """Image inputs before the FC layer: current, target (, previous-altitude view)."""
    return 3 if "prev_embed.weight" in params else 2


def prev_embedding(params: Params, prev_f: torch.Tensor | None, like: torch.Tensor,
                   adapted: Adapted | None = None, rec: Recorder | None = None
                   ) -> torch.Tensor:
    """(B, E) embedding of the previous-altitude view slot; None zero-fills its features
    (as ActorCritic.forward with prev=None: the embedding is ReLU(bias))."""
    f = like.new_zeros(like.shape) if prev_f is None else prev_f
    return F.relu(linear(params, "prev_embed", f, adapted, rec))


def core_step(params: Params, embed_dim: int, state: State, *,
              pre: torch.Tensor | None = None, obs_e: torch.Tensor | None = None,
              tgt_e: torch.Tensor | None = None, prev_e: torch.Tensor | None = None,
              adapted: Adapted | None = None, rec: Recorder | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, State]:
    """One step for B slots from the image part: logits (B, A), value (B,), new state.

    Either ``pre`` (B, H), the FC layer's image columns plus bias (no factors), or the
    embeddings ``obs_e``/``tgt_e`` (and ``prev_e`` with the extra slot) (B, E) for the
    factored FC layer.
    """
    h, c, p = state
    recurrent = "lstm.weight_ih" in params  # NetConfig.recurrent
    act_e = [F.relu(linear(params, "action_embed", p, adapted, rec))] if recurrent else []
    w = params["fc.weight"]
    if pre is not None:
        x = F.relu(pre + affine(act_e[0], w[..., view_slots(params) * embed_dim:])) \
            if recurrent else F.relu(pre)
    else:
        assert obs_e is not None and tgt_e is not None
        parts = [obs_e, tgt_e] + ([] if prev_e is None else [prev_e]) + act_e
        x = F.relu(linear(params, "fc", torch.cat(parts, -1), adapted, rec))
    if not recurrent:  # feed-forward: the heads read the FC layer's output
        x_pi, x_v = head_inputs(x, _head_width(params))
        logit = linear(params, "actor", x_pi, adapted, rec)
        value = linear(params, "critic", x_v, adapted, rec).squeeze(-1)
        return logit, value, (h, c, F.softmax(logit, dim=-1))
    gates = linear(params, "lstm_ih", x, adapted, rec)
    gates = gates + linear(params, "lstm_hh", h, adapted, None, back=rec)
    if rec is not None:  # the hidden matrix shares u = dL/dgates with the input matrix
        rec.add("lstm_hh", h, gates)
    h, c = lstm_cell(gates, c)
    logit = linear(params, "actor", h, adapted, rec)
    value = linear(params, "critic", h, adapted, rec).squeeze(-1)
    return logit, value, (h, c, F.softmax(logit, dim=-1))


def _head_width(params: Params) -> int:
    """Input width H of the actor head, whatever the layout: (A, H) shared, (B, H, A) per
    slot (stored transposed) or (R, A, H) packed runs, with biases (A,), (B, A), (R, A)."""
    return params["actor.weight"].numel() // params["actor.bias"].numel()


def reset_state(state: State, start: torch.Tensor | None) -> State:
    """Zero the state of the slots that begin a new episode (start: (B,) bool).

    No data-dependent branch, so that it runs under ``torch.func.vmap`` (packed runs)."""
    if start is None:
        return state
    keep = (~start).to(state[0].dtype).unsqueeze(-1)
    return (state[0] * keep, state[1] * keep, state[2] * keep)


def sequence_forward(params: Params, embed_dim: int, table: torch.Tensor,
                     view_idx: torch.Tensor, target_idx: torch.Tensor, state: State,
                     starts: torch.Tensor | None = None, prev_table: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, State]:
    """T steps for B slots without per-slot factors, the image part once per view.

    Args:
        table: (C, F) features of the distinct views of the update (with graph when the
            encoder is trained).
        view_idx: (T, B) rows of ``table`` (current views); target_idx: (T, B) or (B,)
            rows of ``table`` (targets; a slot's target changes when it starts an episode).
        state: (h, c, p) before step 0, (B, ...) each.
        starts: (T, B) bool, step t begins a new episode in slot b (state zeroed before it).
        prev_table: (C, F) features of the previous-altitude view at the same cells as
            ``table``'s rows (the extra slot; None zero-fills it).

    Returns:
        logits (T, B, A), values (T, B), the state after step T.
    """
    p, e = params, embed_dim
    w = p["fc.weight"]
    obs_pre = view_table_part(p, e, table, prev_table)                               # (C, H)
    tgt_pre = affine(target_embedding(p, table), w[..., e:2 * e], p["fc.bias"])     # (C, H)
    if target_idx.dim() == 1:
        target_idx = target_idx.unsqueeze(0).expand_as(view_idx)
    logits, values = [], []
    for t in range(view_idx.shape[0]):
        state = reset_state(state, None if starts is None else starts[t])
        logit, value, state = core_step(p, e, state,
                                        pre=obs_pre[view_idx[t]] + tgt_pre[target_idx[t]])
        logits.append(logit)
        values.append(value)
    return torch.stack(logits), torch.stack(values), state


def factored_step(params: Params, embed_dim: int, obs_f: torch.Tensor, tgt_f: torch.Tensor,
                  state: State, adapted: Adapted | None, rec: Recorder | None = None,
                  start: torch.Tensor | None = None, obs_idx: torch.Tensor | None = None,
                  tgt_idx: torch.Tensor | None = None, prev_f: torch.Tensor | None = None,
                  obs_base: torch.Tensor | None = None, tgt_base: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, State]:
    """One step for B slots with per-slot adapted weights, from (B, F) view features.

    Every linear map is evaluated per step (the adapted embeddings differ per slot), and
    recorded in ``rec`` for the inner gradients. ``obs_idx``/``tgt_idx`` (B,): the rows
    of the features in a constant table whose Gram matrix the factors use. ``prev_f``
    (B, F): the extra slot's previous-altitude view features (None zero-fills them).
    ``obs_base``/``tgt_base`` (B, E): the view embeddings' W x + b, when computed
    elsewhere (see :func:`linear`).
    """
    state = reset_state(state, start)
    tgt_e = target_embedding(params, tgt_f, adapted, rec, tgt_idx, tgt_base)
    obs_e = F.relu(linear(params, "obs_embed", obs_f, adapted, rec, obs_idx, obs_base))
    prev_e = prev_embedding(params, prev_f, obs_f, adapted, rec) \
        if view_slots(params) == 3 else None
    return core_step(params, embed_dim, state, obs_e=obs_e, tgt_e=tgt_e, prev_e=prev_e,
                     adapted=adapted, rec=rec)


def factored_forward(params: Params, embed_dim: int, obs_f: torch.Tensor,
                     tgt_f: torch.Tensor, state: State, adapted: Adapted | None,
                     rec: Recorder | None = None, starts: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, State]:
    """T factored steps: obs_f and tgt_f (T, B, F); logits (T, B, A), values (T, B)."""
    logits, values = [], []
    for t in range(obs_f.shape[0]):
        logit, value, state = factored_step(params, embed_dim, obs_f[t], tgt_f[t], state,
                                            adapted, rec,
                                            None if starts is None else starts[t])
        logits.append(logit)
        values.append(value)
    return torch.stack(logits), torch.stack(values), state


def view_table_part(params: Params, embed_dim: int, feats: torch.Tensor,
                    prev_feats: torch.Tensor | None = None) -> torch.Tensor:
    """(C, H) FC-layer image columns of views as the *current* view: W_obs relu(obs_embed)
    (+ W_prev relu(prev_embed) of the previous-altitude view at the same cell)."""
    w = params["fc.weight"]
    e = embed_dim
    out = affine(F.relu(affine(feats, params["obs_embed.weight"], params["obs_embed.bias"])),
                 w[..., :e])
    if view_slots(params) == 3:
        out = out + affine(prev_embedding(params, prev_feats, feats), w[..., 2 * e:3 * e])
    return out


class ActingTables:
    """No-grad image parts of the views met while acting, each computed once per update.

    Valid while the parameters do not change (one rollout). ``features(rows)`` gives the
    (n, F) features of view indices (a frozen table lookup, or the trainable CNN).
    """

    def __init__(self, params: Params, embed_dim: int, n_views: int,
                 features: Callable[[torch.Tensor], torch.Tensor],
                 prev_features: Callable[[torch.Tensor], torch.Tensor | None] | None = None
                 ) -> None:
        self.params = params
        self.embed_dim = embed_dim
        self.features = features
        self.prev_features = prev_features
        w = params["fc.weight"]
        self._filled = torch.zeros(n_views, dtype=torch.bool, device=w.device)
        self._obs = torch.zeros(n_views, w.shape[-2], dtype=w.dtype, device=w.device)
        self._tgt = torch.zeros(n_views, w.shape[-2], dtype=w.dtype, device=w.device)

    @torch.no_grad()
    def _fill(self, rows: torch.Tensor) -> None:
        need = torch.unique(rows[~self._filled[rows]])
        if need.numel():
            p, e = self.params, self.embed_dim
            f = self.features(need)
            self._obs[need] = view_table_part(
                p, e, f, None if self.prev_features is None else self.prev_features(need))
            self._tgt[need] = affine(target_embedding(p, f), p["fc.weight"][..., e:2 * e],
                                     p["fc.bias"])
            self._filled[need] = True

    def pre(self, view_idx: torch.Tensor, target_idx: torch.Tensor) -> torch.Tensor:
        """(B, H) image part of the FC layer for the slots' current and target views."""
        self._fill(torch.cat([view_idx, target_idx]))
        return self._obs[view_idx] + self._tgt[target_idx]


def sample_actions(logits: torch.Tensor, rng: object, live: Any = None) -> torch.Tensor:
    """A draw per row from softmax(logits) (B, A) with a numpy Generator, by the rule of
    :func:`geonav.policy.agent.choose_action` (so B = 1 draws equal the reference's).

    ``live`` (B,) bool: draw for those rows only (the others get action 0), so a run's
    stream does not depend on how long masked rows keep stepping (SAVN's rounds, packed:
    ``rng`` then draws each run's live rows from its own generator)."""
    import numpy as np

    probs = torch.softmax(logits.detach(), dim=-1).to("cpu", torch.float64).numpy()
    cdf = np.cumsum(probs, axis=1)
    if live is None:
        u = rng.random(probs.shape[0])  # type: ignore[attr-defined]
    else:
        u = np.zeros(probs.shape[0])
        u[live] = rng.random_live(live) if hasattr(rng, "random_live") \
            else rng.random(int(live.sum()))  # type: ignore[attr-defined]
    x = u * cdf[:, -1]
    a = (cdf <= x[:, None]).sum(1)
    return torch.from_numpy(np.minimum(a, probs.shape[1] - 1))
