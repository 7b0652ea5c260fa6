"""Where pick_place, stack, pick_into_bin, peg_insert, push and press_button episodes fail, sorted by what the objects
did.

Why: the success rate says how often a policy fails, not where; the videos show one episode. The
simulator's object positions (``observation.environment_state``: pick_place's target cube, distractor cube
and plate; stack's cube to move, cube to stack on and distractor; push's two pucks and goal square; xyz each) are in
every evaluated step, so each episode is sorted, from its trajectory alone, into the first of (pick_place)

* ``success``;
* ``wrong object``: the distractor moved more than 1 cm;
* ``untouched``: the target cube never moved more than 1 cm (the grasp missed it);
* ``not lifted``: the target moved but never rose 2 cm above the table;
* ``held at the end``: lifted, and still in the air when time ran out;
* ``dropped off the plate``: lifted, and at the end lying off the plate;
* ``on the plate, not released``: lifted and on the plate, the gripper still touching it.

and for stack the same first five (the cube to move as the target), then

* ``set down beside it``: lifted and held over the lower cube (centres within the task's 2 cm at some step,
  the carried cube above the lower one's top), yet at the end not on it: the place itself missed;
* ``set down elsewhere``: lifted, never held over the lower cube within 2 cm;
* ``on the lower cube, not released``: stacked, the gripper still touching it.

and for pick_into_bin the same first five (the named object as the target, the distractor that moved most as the
distractor), then

* ``at the bin, not in it``: lifted, and at the end within the bin's footprint (at any yaw) yet not resting inside
  (on a wall, or still held);
* ``dropped away from the bin``: lifted, and at the end outside that footprint.

and peg_insert (the peg and the fixture; no distractor):

* ``success`` and ``untouched`` as above;
* ``not lifted``: the peg moved but its centre never rose 2 cm above its resting height (the task's own "lifted");
* ``at the block, not inserted``: lifted, and at the end within the fixture's footprint (at any yaw), held over it,
  resting on its top or jammed in the hole short of the task's 2 cm;
* ``held away from the block``: lifted, and at the end still lifted, outside that footprint;
* ``dropped away from the block``: lifted, and at the end down again, outside that footprint.

and push (the named puck as the target; the goal square's centre):

* ``success``, ``wrong object`` and ``untouched`` as above;
* ``passed through the square``: the puck's centre came within the square's half-width of its centre at some step,
  yet ended outside the square (pushed on past it, or pulled back out);
* ``pushed short``: it never came that close and ended nearer the goal than it started;
* ``pushed astray``: it never came that close and ended no nearer the goal than it started.

and press_button (the named button first, then the two others; the caps' depressions):

* ``success``;
* ``wrong button``: another button's cap went down more than 1 mm;
* ``pressed partway``: the named cap went down more than 1 mm, never the task's 8 mm;
* ``not pressed``: the named cap never went down more than 1 mm.

For peg_insert also, per class, how well the peg was ever aligned over the hole while held above the block: the
smallest xy offset from the hole's axis and the yaw between peg and hole at that step (the hole leaves 2.5 mm a
side; a square peg centred in it may turn 13.6 degrees).

Beside each class's count, how far the end effector's orientation has turned from its start by the end of the
episode (median and range, degrees; from ``observation.state``): a policy pushing on against a rim or the table
tilts the wrist.

``--sheet PNG`` also draws, for the first episodes of each class, the cameras at four moments of the
episode (its last step included), so the classes can be looked at, not only counted.

    .venv/bin/python experiments/failure_modes.py --policy runs/train/T/policy.pt --seed 5000 --episodes 30 \
        [--max-steps N] [--sheet runs/eval/T/failure_modes.png]
    .venv/bin/python experiments/failure_modes.py --dataset runs/data/peg_insert_oracle_200  # the expert's alignment
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import statistics

import matplotlib
import torch
from tensordict import TensorDictBase

from dust_rl.data import DemoDataset
from dust_rl.envs.env import STATE_PARTS
from dust_rl.envs.tasks import peg_insert, pick_into_bin, press_button, push, stack
from dust_rl.envs.tasks.pick_place import CUBE_HALF, PLATE_RADIUS
from dust_rl.evaluate.closed_loop import EvalConfig, evaluate_task, prepare
from dust_rl.keys import ENV_STATE_KEY, IMAGE_KEY, STATE_KEY
from dust_rl.runtime.settings import RuntimeSettings

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

MOVED = 0.01  # m
PUSHED = 0.001  # m: a cap pushed in this far was touched (it rests at -0.2 mm against its preload)
LIFTED = CUBE_HALF + 0.02  # m: the task's own "lifted" height of the cube's centre
PEG_LIFTED = peg_insert.PEG_HALF[2] + 0.02  # m: peg_insert's own "lifted" height of the peg's centre
FIRST_MODES = ("success", "wrong object", "untouched", "not lifted", "held at the end")
MODES = {"pick_place": (*FIRST_MODES, "dropped off the plate", "on the plate, not released"),
         "stack": (*FIRST_MODES, "set down beside it", "set down elsewhere", "on the lower cube, not released"),
         "pick_into_bin": (*FIRST_MODES, "at the bin, not in it", "dropped away from the bin"),
         "peg_insert": ("success", "untouched", "not lifted", "at the block, not inserted", "held away from the block",
                        "dropped away from the block"),
         "push": ("success", "wrong object", "untouched", "passed through the square", "pushed short", "pushed astray"),
         "press_button": ("success", "wrong button", "pressed partway", "not pressed")}
MOMENTS = (0.25, 0.5, 0.75, 1.0)  # fractions of an episode drawn on the sheet


def contact_mode(target: torch.Tensor, distractor: torch.Tensor | None, success: bool) -> str | None:
    """Success, or which object the policy failed to move right, from both objects' positions [T, 3] (a task
    without a distractor passes None), if either."""
    if success:
        return "success"
    if distractor is not None and (distractor[:, :2] - distractor[0, :2]).norm(dim=-1).max() > MOVED:
        return "wrong object"
    if (target - target[0]).norm(dim=-1).max() <= MOVED:
        return "untouched"
    return None


def first_mode(target: torch.Tensor, distractor: torch.Tensor, success: bool) -> str | None:
    """The class shared by the grasping tasks from the target's and the distractor's positions [T, 3], if one
    applies."""
    if mode := contact_mode(target, distractor, success):
        return mode
    if target[:, 2].max() <= LIFTED:
        return "not lifted"
    if target[-1, 2] > LIFTED:
        return "held at the end"
    return None


def pick_place_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one pick_place episode from its object positions [T, 9] (target, distractor, plate)."""
    target, distractor, plate = env_state[:, 0:3], env_state[:, 3:6], env_state[:, 6:9]
    if mode := first_mode(target, distractor, success):
        return mode
    if (target[-1, :2] - plate[-1, :2]).norm() >= PLATE_RADIUS - 0.01:  # the task's own on-plate radius
        return "dropped off the plate"
    return "on the plate, not released"


def stack_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one stack episode from its object positions [T, 9] (cube to move, lower cube, distractor)."""
    target, lower, distractor = env_state[:, 0:3], env_state[:, 3:6], env_state[:, 6:9]
    if mode := first_mode(target, distractor, success):
        return mode
    offset = (target[:, :2] - lower[:, :2]).norm(dim=-1)
    if offset[-1] < stack.XY_TOLERANCE and target[-1, 2] > lower[-1, 2] + stack.CUBE_HALF:
        return "on the lower cube, not released"
    over = target[:, 2] > lower[:, 2] + 2 * stack.CUBE_HALF  # its bottom face above the lower cube's top
    if (offset[over] < stack.XY_TOLERANCE).any():
        return "set down beside it"
    return "set down elsewhere"


def pick_into_bin_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one pick_into_bin episode from its object positions [T, 12] (target, two distractors, bin)."""
    target, distractors, bin_ = env_state[:, 0:3], (env_state[:, 3:6], env_state[:, 6:9]), env_state[:, 9:12]
    moved = [(d[:, :2] - d[0, :2]).norm(dim=-1).max() for d in distractors]
    if mode := first_mode(target, distractors[int(moved[1] > moved[0])], success):
        return mode
    if (target[-1, :2] - bin_[-1, :2]).norm() <= pick_into_bin.BIN_OUTER_HALF * 2 ** 0.5:
        return "at the bin, not in it"
    return "dropped away from the bin"


def peg_insert_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one peg_insert episode from its positions [T, 6] (peg, fixture)."""
    peg, fixture = env_state[:, 0:3], env_state[:, 3:6]
    if mode := contact_mode(peg, None, success):
        return mode
    if peg[:, 2].max() <= PEG_LIFTED:
        return "not lifted"
    if (peg[-1, :2] - fixture[-1, :2]).norm() <= peg_insert.FIXTURE_HALF * 2 ** 0.5:
        return "at the block, not inserted"
    return "held away from the block" if peg[-1, 2] > PEG_LIFTED else "dropped away from the block"


def peg_alignment(env_state: torch.Tensor) -> tuple[float, float] | None:
    """The peg's best alignment over the hole while held above the block's top: the smallest xy offset from the
    hole's axis (mm) and, at that step, the yaw between peg and hole (degrees, up to their square symmetry); None
    for a state without the yaws (datasets from before they were added) or a peg never above the block."""
    if env_state.shape[-1] < 10:
        return None
    peg, fixture = env_state[:, 0:3], env_state[:, 3:6]
    above = peg[:, 2] - peg_insert.PEG_HALF[2] > peg_insert.FIXTURE_HEIGHT
    if not above.any():
        return None
    offset = (peg[:, :2] - fixture[:, :2]).norm(dim=-1).masked_fill(~above, float("inf"))
    step = int(offset.argmin())
    peg_yaw, hole_yaw = (math.atan2(*env_state[step, i:i + 2].tolist()) / 4 for i in (6, 8))  # (sin, cos) of 4 yaw
    turn = math.degrees(peg_yaw - hole_yaw) % 90
    return 1000 * float(offset[step]), min(turn, 90 - turn)


def push_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one push episode from its positions [T, 9] (target puck, distractor puck, goal square)."""
    target, distractor, goal = env_state[:, 0:3], env_state[:, 3:6], env_state[:, 6:9]
    if mode := contact_mode(target, distractor, success):
        return mode
    to_goal = (target[:, :2] - goal[:, :2]).norm(dim=-1)
    if to_goal.min() < push.GOAL_HALF:
        return "passed through the square"
    return "pushed short" if to_goal[-1] < to_goal[0] else "pushed astray"


def press_button_mode(env_state: torch.Tensor, success: bool) -> str:
    """The class of one press_button episode from its buttons [T, 4 * 3] (base xyz, cap depression; named first)."""
    depression = env_state.view(env_state.shape[0], press_button.N_BUTTONS, 4)[..., 3].amax(0)
    if success:
        return "success"
    if (depression[1:] > PUSHED).any():
        return "wrong button"
    return "pressed partway" if depression[0] > PUSHED else "not pressed"


CLASSIFIERS = {"pick_place": pick_place_mode, "stack": stack_mode, "pick_into_bin": pick_into_bin_mode,
               "peg_insert": peg_insert_mode, "push": push_mode, "press_button": press_button_mode}


def end_tilt(trajectory: TensorDictBase) -> float:
    """Degrees between the end effector's orientation after the episode's last step and at its start."""
    quaternion = slice(-len(STATE_PARTS) + 3, -1)  # wxyz, after the position, before the opening
    start = trajectory.get(STATE_KEY)[0, quaternion].double()
    end = trajectory.get(("next", *STATE_KEY))[-1, quaternion].double()
    return math.degrees(2 * math.acos(min(1.0, abs(float(start @ end)))))


def contact_sheet(trajectories: dict[int, TensorDictBase], modes: dict[int, str], order: tuple[str, ...],
                  cameras: tuple[str, ...], per_mode: int, path: pathlib.Path) -> None:
    """One row per episode (the first ``per_mode`` of each class, classes in ``order``), the cameras side by side
    at each moment."""
    rows = [(seed, mode) for mode in order for seed in [s for s, m in modes.items() if m == mode][:per_mode]]
    figure, axes = plt.subplots(len(rows), len(MOMENTS), figsize=(2.4 * len(cameras) * len(MOMENTS), 2.6 * len(rows)),
                                squeeze=False)
    for (seed, mode), row in zip(rows, axes):
        trajectory = trajectories[seed]
        for moment, axis in zip(MOMENTS, row):
            step = round(moment * (trajectory.shape[0] - 1))
            views = [trajectory[step].get((*IMAGE_KEY, camera)).permute(1, 2, 0) for camera in cameras]
            axis.imshow(torch.cat(views, dim=1).numpy())
            axis.set_title(f"seed {seed}, {mode}, step {step}" if moment == MOMENTS[0] else f"step {step}",
                           fontsize=8)
            axis.axis("off")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=80)
    plt.close(figure)


def print_alignments(classes: dict[str, list[tuple[float, float] | None]]) -> None:
    """Per class, the median and range of :func:`peg_alignment`'s offset and yaw over its episodes."""
    print("peg over the hole at its best (xy offset mm, yaw degrees: median, range), per class:")
    for name, measured in classes.items():
        rows = [row for row in measured if row is not None]
        if rows:
            mm, deg = (sorted(column) for column in zip(*rows))
            print(f"  {name} ({len(rows)}): {statistics.median(mm):.1f}, {mm[0]:.1f}-{mm[-1]:.1f} mm; "
                  f"{statistics.median(deg):.1f}, {deg[0]:.1f}-{deg[-1]:.1f} deg")


def dataset_alignments(root: pathlib.Path) -> None:
    """:func:`print_alignments` of a peg_insert dataset's demonstrations, from their stored object state."""
    dataset = DemoDataset(root)
    state = dataset.data.get(ENV_STATE_KEY)
    print_alignments({"demonstrations": [peg_alignment(state[start:start + length].float()) for start, length
                                         in zip(dataset.episode_starts.tolist(), dataset.lengths.tolist())]})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--policy", type=pathlib.Path)
    which.add_argument("--dataset", type=pathlib.Path, help="a peg_insert dataset: its demonstrations' alignment only")
    parser.add_argument("--seed", type=int, default=5000)
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--max-steps", type=int, default=None, help="time limit per episode (default: the task's)")
    parser.add_argument("--sheet", type=pathlib.Path, default=None, help="also draw the episodes into this PNG")
    parser.add_argument("--per-class", type=int, default=3, help="episodes per class on the sheet")
    args = parser.parse_args()
    if args.dataset:
        dataset_alignments(args.dataset)
        return
    config = EvalConfig(policy=args.policy, seed=args.seed, episodes=args.episodes, workers=1, videos=args.episodes,
                        max_steps=args.max_steps, runtime=RuntimeSettings(threads=args.threads, device="cpu"))
    torch.set_num_threads(args.threads)
    policy, setup = prepare(config)
    if len(setup.tasks) != 1 or setup.tasks[0] not in CLASSIFIERS:
        raise SystemExit(f"{args.policy}: trained on {setup.tasks}; this script reads one of {sorted(CLASSIFIERS)}")
    task = setup.tasks[0]
    episodes, trajectories, _, _ = evaluate_task(setup, task, policy, config)
    modes = {e.seed: CLASSIFIERS[task](trajectories[e.seed].get(("next", *ENV_STATE_KEY)), e.success)
             for e in episodes}
    tilts = {seed: end_tilt(trajectory) for seed, trajectory in trajectories.items()}
    print(f"{args.policy}, seeds {args.seed}..{args.seed + args.episodes - 1} (count; end effector turned by the end, "
          "degrees: median, range):")
    for mode in MODES[task]:
        turned = sorted(tilts[seed] for seed, m in modes.items() if m == mode)
        tilt = f"; {statistics.median(turned):.1f}, {turned[0]:.1f}-{turned[-1]:.1f}" if turned else ""
        print(f"  {mode}: {len(turned)}{tilt}")
    if task == "peg_insert":
        aligned = {e.seed: peg_alignment(trajectories[e.seed].get(("next", *ENV_STATE_KEY))) for e in episodes}
        print_alignments({mode: [aligned[seed] for seed, m in modes.items() if m == mode] for mode in MODES[task]})
    print(json.dumps(modes))
    if args.sheet:
        contact_sheet(trajectories, modes, MODES[task], policy.cameras, args.per_class, args.sheet)
        print(f"sheet: {args.sheet}")


if __name__ == "__main__":
    main()
