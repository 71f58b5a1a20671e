"""Where greedy episodes fail: train geonav's PPO on a bench task, then sort the greedy
failures over every start into 'wall' (more than 5 refused moves: the view does not
change, so neither does a feed-forward argmax) and '2-cycle' (the last 10 actions use two
actions), per target; the sampled policy's success beside it (docs/learning.md §14).

    python bench/diagnose_greedy.py                       # feed-forward net, 49,152 steps
    python bench/diagnose_greedy.py --recurrent --steps 65536
    python bench/diagnose_greedy.py --sb3                 # SB3 PPO's policy, same task
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_learning import VIEW_TASKS, sb3_episodes, view_task  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="view45-campus", choices=sorted(VIEW_TASKS))
    ap.add_argument("--targets", type=int, default=8)
    ap.add_argument("--steps", type=int, default=49152)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--recurrent", action="store_true", help="the paper's LSTM network")
    ap.add_argument("--sb3", action="store_true", help="SB3 PPO (MultiInputPolicy) instead")
    ap.add_argument("--cache", default=str(ROOT / "bench" / ".cache"))
    args = ap.parse_args()

    import torch

    from geonav.policy.batched.ppo import PPOConfig
    from geonav.policy.config import NetConfig
    from geonav.policy.engine import build_trainer
    from geonav.policy.envs import EnvFactory
    from geonav.policy.evaluation import all_starts, evaluate_lockstep

    torch.set_num_threads(1)
    factory = EnvFactory(*view_task(Path(args.cache), args.task, args.targets))
    env = factory()
    starts = all_starts(env, None, args.seed)
    if args.sb3:
        from stable_baselines3 import PPO

        sb3 = PPO("MultiInputPolicy", factory(), seed=args.seed, verbose=0, device="cpu")
        sb3.learn(total_timesteps=args.steps)
    else:
        net = NetConfig(obs_size_px=64, recurrent=args.recurrent)
        cfg = PPOConfig(episodes=10 ** 7, total_steps=args.steps, workers=0,
                        seed=args.seed, eval_every=0)
        model = build_trainer("ppo", "batched", factory, net, cfg, tensorboard=False,
                              keep_records=False).train().model
    for greedy in (True, False):
        episodes = sb3_episodes(sb3, env, starts, greedy) if args.sb3 else \
            evaluate_lockstep(model, env, starts, greedy=greedy, seed=args.seed).episodes
        fails = [e for e in episodes if not e["success"]]
        sr = 1.0 - len(fails) / len(episodes)
        print(f"{'greedy' if greedy else 'sampled'} SR {sr:.3f} over "
              f"{len(starts)} starts; {len(fails)} failures, "
              f"{np.mean([e['collisions'] for e in fails]) if fails else 0:.1f} refused "
              "moves each on average")
        if greedy:
            kinds: collections.Counter[str] = collections.Counter()
            for e in fails:
                if e["collisions"] > 5:
                    kinds["wall"] += 1
                elif len(set(e["actions"][-10:])) == 2:
                    kinds["2-cycle"] += 1
                else:
                    kinds["other"] += 1
            print(f"  greedy failures: {dict(kinds)}; per target: "
                  f"{dict(sorted(collections.Counter(e['task_index'] for e in fails).items()))}")


if __name__ == "__main__":
    main()
