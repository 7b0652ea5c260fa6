"""How precise must perception be? The privileged-state oracle evaluated with its object state misplaced.

The oracle policy (trained on ``dust-rl collect --privileged-state`` data) reads the objects' true positions.
Here each evaluation episode offsets every object coordinate it reads by one Gaussian draw of standard
deviation sigma (``DustEnv(privileged_noise=sigma)``), as a read-out that is consistently off by about sigma
would. The success rate against sigma says how far a learnt read-out may err before grasps fail.

    .venv/bin/python experiments/oracle_noise.py --policy runs/train/pick_place_oracle/policy.pt \\
        --out runs/eval/oracle_noise --sigmas 0 0.01 0.02 0.04 --episodes 20 --seed 5000
"""

from __future__ import annotations

import argparse
import pathlib

from dust_rl.agents import load_policy, save_policy
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="an oracle policy (trained with --privileged-state data)")
    parser.add_argument("--out", required=True, help="folder for one evaluation per sigma")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.01, 0.02, 0.04], help="metres")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=5000, help="first evaluation seed (validation: 5000)")
    args = parser.parse_args()
    policy = load_policy(args.policy)
    if not policy.info.get("env_kwargs", {}).get("privileged_state"):
        raise SystemExit(f"{args.policy} was not trained on privileged-state data")
    out = pathlib.Path(args.out)
    rows = []
    for sigma in args.sigmas:
        policy.info["env_kwargs"] = {**policy.info["env_kwargs"], "privileged_noise": sigma}
        path = save_policy(policy, out / f"sigma{sigma:g}" / "policy.pt")
        report = evaluate(EvalConfig(policy=path, out=path.parent, episodes=args.episodes, seed=args.seed,
                                     workers=1, videos=1))
        rows.append((sigma, report["overall"]))
    print("| object offset sigma (cm) | success | 95% CI |\n|---|---|---|")
    for sigma, o in rows:
        print(f"| {100 * sigma:g} | {100 * o['success_rate']:.0f}% ({o['successes']}/{o['episodes']}) | "
              f"{100 * o['ci95_low']:.0f}-{100 * o['ci95_high']:.0f}% |")


if __name__ == "__main__":
    main()
