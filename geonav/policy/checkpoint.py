"""Policy checkpoints (DESIGN.md "Policy checkpoints").

A checkpoint is ``torch.save`` of a plain dict::

    {"format": "geonav-policy", "format_version": 1,
     "model": state_dict (tensors), "optimizer": Adam state_dict or None,
     "rng": RNG states for an exact resume or None, "meta": JSON-able dict,
     "extra": name -> state_dict of auxiliary modules (SAVN's learned loss) or None}

``meta`` holds the architecture (``net``), the encoder, the observation size,
field of view, action meanings, the altitude and lattice step it was trained
for, the algorithm, episodes seen, the geonav and torch versions, the scene id
and the task fingerprint. It loads with ``torch.load(weights_only=True)``;
writes are atomic (temp file + ``os.replace``), so a crash never leaves a
half-written checkpoint under the final name.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from geonav.errors import CheckpointError, ConfigError
from geonav.policy.config import NetConfig, from_dict
from geonav.policy.encoders import FrozenEncoder, build_frozen_encoder
from geonav.policy.model import ActorCritic, arch_meta

log = logging.getLogger(__name__)

FORMAT = "geonav-policy"
FORMAT_VERSION = 1


@dataclass
class Checkpoint:
    """A loaded, validated checkpoint."""

    path: Path
    meta: dict[str, Any]
    model_state: dict[str, torch.Tensor]
    optimizer_state: dict[str, Any] | None
    rng: dict[str, Any] | None
    extra: dict[str, dict[str, torch.Tensor]] | None = None
    """Auxiliary modules' state_dicts by name (e.g. SAVN's ``"interaction_loss"``)."""

    @property
    def net_config(self) -> NetConfig:
        d = {k: v for k, v in self.meta["net"].items() if k != "class"}
        try:
            return from_dict(NetConfig, d)
        except (ConfigError, TypeError) as err:
            raise CheckpointError(f"checkpoint {self.path} has an invalid architecture record "
                                  f"{d}: {err}") from err

    @property
    def episodes(self) -> int:
        return int(self.meta.get("episodes", 0))

    def build_model(self) -> ActorCritic:
        """The network with the checkpoint's weights (eval mode)."""
        model = ActorCritic(self.net_config)
        try:
            model.load_state_dict(self.model_state, strict=True)
        except RuntimeError as err:
            raise CheckpointError(f"checkpoint {self.path} weights do not fit its architecture "
                                  f"record: {err}") from err
        return model.eval()

    def build_encoder(self) -> FrozenEncoder | None:
        """The frozen encoder the policy was trained with (None for the trainable CNN)."""
        enc = build_frozen_encoder(self.net_config)
        want = self.meta.get("encoder", {})
        if enc is not None and want.get("weights_sha256") and \
                enc.spec.get("weights_sha256") != want["weights_sha256"]:
            raise CheckpointError(f"checkpoint {self.path} was trained with encoder weights "
                                  f"sha256 {want['weights_sha256'][:12]}..., but "
                                  f"{enc.spec.get('weights')} has another; pass the same file")
        return enc


def task_fingerprint(tasks: list[Any]) -> str:
    """A short hash of a list of ``NavTask`` (their JSON form)."""
    blob = json.dumps([t.to_dict() for t in tasks], sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def env_meta(env: Any) -> dict[str, Any]:
    """What a checkpoint records about the environment it was trained on."""
    u = env.unwrapped
    tasks = list(getattr(u, "tasks", []))
    alts = sorted({float(t.alt_m) for t in tasks})
    steps = sorted({float(t.step_m) for t in tasks})
    camera = getattr(u, "camera", None)
    scene = getattr(u, "scene", None)
    return {
        "obs_size_px": int(env.observation_space["image"].shape[0]),
        "fov_deg": float(camera.fov_deg) if camera is not None else None,
        "n_actions": int(env.action_space.n),
        "action_meanings": list(getattr(u, "action_meanings", [])),
        "alt_m": alts[0] if len(alts) == 1 else alts,
        "step_m": steps[0] if len(steps) == 1 else steps,
        "scene_id": getattr(scene, "scene_id", None),
        "scene_name": getattr(scene, "name", None),
        "tasks": [t.name for t in tasks],
        "task_fingerprint": task_fingerprint(tasks) if tasks else None,
    }


def make_meta(net_cfg: NetConfig, encoder: FrozenEncoder | None, env: Any, *, algorithm: str,
              episodes: int, config: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``meta`` dict of a checkpoint."""
    import geonav

    meta = env_meta(env)
    meta.update({
        "net": arch_meta(net_cfg),
        "encoder": encoder.spec if encoder is not None else {"kind": "cnn", "trainable": True},
        "algorithm": algorithm,
        "episodes": int(episodes),
        "geonav_version": geonav.__version__,
        "torch_version": str(torch.__version__),
        "config": config or {},
    })
    return meta


def save_checkpoint(path: str | os.PathLike[str], model_state: dict[str, torch.Tensor],
                    meta: dict[str, Any], optimizer_state: dict[str, Any] | None = None,
                    rng: dict[str, Any] | None = None,
                    extra: dict[str, dict[str, torch.Tensor]] | None = None) -> Path:
    """Write a checkpoint atomically (temp file in the same folder + ``os.replace``).

    ``extra`` holds auxiliary modules' state_dicts (name -> state_dict), kept beside the
    policy so that ``model`` always loads into a plain :class:`ActorCritic`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = json.loads(json.dumps(meta))  # plain JSON types only; fails before any write
    blob = {"format": FORMAT, "format_version": FORMAT_VERSION,
            "model": {k: v.detach().clone() for k, v in model_state.items()},
            "optimizer": optimizer_state, "rng": rng, "meta": meta}
    if extra:
        blob["extra"] = {name: {k: v.detach().clone() for k, v in sd.items()}
                         for name, sd in extra.items()}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(blob, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike[str]) -> Checkpoint:
    """Load and validate a checkpoint (``weights_only=True``).

    Raises:
        CheckpointError: missing, truncated or corrupt file, or not a geonav policy.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile,
            __import__("pickle").UnpicklingError) as err:
        found = re.search(r"GLOBAL ([\w.]+)", str(err))
        if found:
            # torch's message advises weights_only=False: exactly what would run the payload
            raise CheckpointError(
                f"checkpoint {path} holds more than weights (a reference to the Python "
                f"callable {found.group(1)!r}, which loading would call); geonav never runs "
                "code from a checkpoint, and this one was not written by geonav or was "
                "altered: do not load it elsewhere either; use a checkpoint that geonav "
                "train wrote") from None
        lines = [ln.strip() for ln in str(err).splitlines() if ln.strip() and not re.search(
            r"weights_only|torch\.load|file an issue|safe_globals|trusted source", ln)]
        why = (lines[0] if lines else type(err).__name__)[:200]
        raise CheckpointError(f"checkpoint {path} is corrupt or truncated and cannot be read "
                              f"({type(err).__name__}: {why}); "
                              "use another checkpoint, e.g. the run's checkpoints/latest.pt") \
            from err
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a geonav policy checkpoint (no "
                              f"format={FORMAT!r} key)")
    if blob.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format_version "
                              f"{blob.get('format_version')}, this geonav reads {FORMAT_VERSION}")
    meta, state = blob.get("meta"), blob.get("model")
    if not isinstance(meta, dict) or not isinstance(meta.get("net"), dict):
        raise CheckpointError(f"checkpoint {path} has no architecture record in its meta")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor)
                                              for v in state.values()):
        raise CheckpointError(f"checkpoint {path} has no weights dict")
    ckpt = Checkpoint(path, meta, state, blob.get("optimizer"), blob.get("rng"),
                      blob.get("extra"))
    check_weights(ckpt)
    return ckpt


def check_weights(ckpt: Checkpoint) -> None:
    """Refuse weights that cannot act: non-finite values, or a network other than the one
    its architecture record and metadata describe.

    Raises:
        CheckpointError: naming the first offending tensor and what to do.
    """
    path, cfg = ckpt.path, ckpt.net_config  # net_config validates the architecture record
    tensors = [(k, v) for k, v in ckpt.model_state.items()] + [
        (f"{name}.{k}", v) for name, sd in (ckpt.extra or {}).items() if isinstance(sd, dict)
        for k, v in sd.items() if isinstance(v, torch.Tensor)]
    bad = [k for k, v in tensors if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(
            f"checkpoint {path} holds non-finite weights (NaN or inf in {len(bad)} of "
            f"{len(tensors)} tensors, first {bad[0]!r}): its training diverged; use an earlier "
            "checkpoint of the run (checkpoints/episode_*.pt) or train again")
    for key, want in (("obs_size_px", cfg.obs_size_px), ("n_actions", cfg.n_actions)):
        have = ckpt.meta.get(key)
        if have is not None and have != want:
            raise CheckpointError(f"checkpoint {path} says {key}={have!r} in its meta but its "
                                  f"network has {key}={want!r}; the file was altered, use "
                                  "another checkpoint")
    try:
        with torch.device("meta"):  # shapes only, nothing allocated
            expected = {k: tuple(v.shape) for k, v in ActorCritic(cfg).state_dict().items()}
    except Exception:  # noqa: BLE001 - the strict load in build_model still checks
        return
    have = {k: tuple(v.shape) for k, v in ckpt.model_state.items()}
    if have != expected:
        missing = sorted(set(expected) - set(have))
        extra = sorted(set(have) - set(expected))
        shape = next((f"{k} is {have[k]}, its architecture needs {expected[k]}"
                      for k in expected if k in have and have[k] != expected[k]), "")
        detail = "; ".join(x for x in (
            f"missing {missing[:3]}" if missing else "", f"unexpected {extra[:3]}" if extra
            else "", shape) if x)
        raise CheckpointError(f"checkpoint {path} weights do not fit its architecture record "
                              f"({detail}); the file was altered, use another checkpoint")


def check_compatible(meta: dict[str, Any], env: Any, *, path: Any = "checkpoint",
                     net_cfg: NetConfig | None = None) -> None:
    """Refuse a checkpoint whose observation size, action set or encoder differ from the env's.

    Args:
        meta: the checkpoint's meta.
        env: the environment the policy will act in.
        path: how to name the checkpoint in messages.
        net_cfg: the architecture a caller asks for (resume); compared with the checkpoint's.

    Raises:
        CheckpointError: on any mismatch, naming both values.
    """
    em = env_meta(env)
    if int(meta.get("obs_size_px", -1)) != em["obs_size_px"]:
        raise CheckpointError(f"{path} was trained on {meta.get('obs_size_px')} px observations, "
                              f"the environment gives {em['obs_size_px']} px; use --obs-size "
                              f"{meta.get('obs_size_px')}")
    if int(meta.get("n_actions", -1)) != em["n_actions"] or (
            em["action_meanings"] and meta.get("action_meanings")
            and list(meta["action_meanings"]) != em["action_meanings"]):
        raise CheckpointError(f"{path} was trained with actions {meta.get('action_meanings')}, "
                              f"the environment has {em['action_meanings']}")
    if net_cfg is not None:
        ck = meta["net"]
        for key in ("encoder", "obs_size_px", "embed_dim", "action_embed_dim", "hidden_size",
                    "lstm_size", "n_actions"):
            if ck.get(key) != getattr(net_cfg, key):
                raise CheckpointError(f"{path} has {key}={ck.get(key)!r}, but this run asks for "
                                      f"{key}={getattr(net_cfg, key)!r}")
        # absent from checkpoints written before the option existed: its default then
        for key, default in (("prev_view_input", False), ("recurrent", True),
                             ("separate_critic", False)):
            if bool(ck.get(key, default)) != getattr(net_cfg, key):
                raise CheckpointError(f"{path} has {key}={bool(ck.get(key, default))}, but this "
                                      f"run asks for {key}={getattr(net_cfg, key)}")
    if meta.get("scene_id") and em["scene_id"] and meta["scene_id"] != em["scene_id"]:
        log.info("%s was trained on scene %s, now used on %s", path, meta.get("scene_name"),
                 em["scene_name"])
