"""Environment speed: DustEnv control steps/s beside a bare MuJoCo + mink loop, and frame times.

The bare loop drives the same compiled scene with the same mink tasks,
limits and camera renders but none of the environment's code (action
checks, observation dicts, success tests), so ``env / bare`` is the
wrapper's overhead. Any number of end effectors (7 action numbers each).
Pinned to one CPU core by default, as the targets ask.

    python -m dust_rl.bench.env_speed [--env DustHumanoid-v0] [--steps 600] [--tasks pick_place ...]
"""

from __future__ import annotations

import argparse
import os
import time

import mink
import mujoco
import numpy as np

from dust_rl.envs import DustEnv
from dust_rl.envs.env import MAX_ROTATION, MAX_TRANSLATION
from dust_rl.envs.rendering import CameraRenderer


def _actions(steps: int, action_dim: int) -> np.ndarray:
    # Smooth random motion that stays in the workspace.
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.5, 0.5, (steps, action_dim)).astype(np.float32)
    translation = np.arange(action_dim) % 7 < 3
    actions[:, translation] *= np.sign(np.sin(np.arange(steps) / 20.0))[:, None]
    return actions


def time_env(env: DustEnv, actions: np.ndarray) -> float:
    env.reset(seed=0)
    start = time.perf_counter()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    return len(actions) / (time.perf_counter() - start)


def time_bare_loop(env: DustEnv, actions: np.ndarray) -> float:
    """The same physics, IK and renders, written directly against MuJoCo and mink."""
    env.reset(seed=0)
    model, data, controller = env.model, env.data, env.controller
    sites = [model.site(ee.site).id for ee in env.robot.end_effectors]
    closures = [(np.array([model.actuator(a).id for a in ee.actuators]), np.array(ee.open_ctrl),
                 np.array(ee.closed_ctrl)) for ee in env.robot.end_effectors]
    arm_ctrl = [model.actuator(a).id for a in env.robot.arm_actuators]
    sim_qadr = [model.joint(controller.model.joint(j).name).qposadr[0] for j in range(controller.model.njnt)]
    arm_qadr = [controller.model.joint(j).qposadr[0] for j in env.robot.arm_joints]
    tasks = [*controller.frame_tasks, controller.posture_task]
    renderer = CameraRenderer(model, *env.image_shape[:2]) if env.obs_mode == "rgb" else None
    rotation = np.empty(4)
    start = time.perf_counter()
    for action in actions:
        for i, (frame_task, site) in enumerate(zip(controller.frame_tasks, sites)):
            rotation[:] = (1, 0, 0, 0)
            mujoco.mju_quatIntegrate(rotation, action[7 * i + 3: 7 * i + 6].astype(float) * MAX_ROTATION, 1.0)
            current = mink.SE3.from_rotation_and_translation(
                mink.SO3.from_matrix(data.site_xmat[site].reshape(3, 3)), data.site_xpos[site])
            translation = current.translation() + action[7 * i: 7 * i + 3] * MAX_TRANSLATION
            frame_task.set_target(mink.SE3.from_rotation_and_translation(mink.SO3(rotation) @ current.rotation(),
                                                                          translation))
        controller.configuration.update(data.qpos[sim_qadr])
        try:
            velocity = mink.solve_ik(controller.configuration, tasks, controller.dt, controller.solver,
                                     damping=1e-3, limits=controller.limits)
            controller.configuration.integrate_inplace(velocity, controller.dt)
        except mink.NoSolutionFound:  # hold the previous targets, as a bare loop would
            pass
        data.ctrl[arm_ctrl] = controller.configuration.q[arm_qadr]
        for i, (ids, open_ctrl, closed_ctrl) in enumerate(closures):
            data.ctrl[ids] = open_ctrl + (action[7 * i + 6] + 1.0) / 2.0 * (closed_ctrl - open_ctrl)
        mujoco.mj_step(model, data, nstep=env.n_substeps)
        if renderer is not None:
            for camera in env.cameras:
                renderer.render(data, camera)
    rate = len(actions) / (time.perf_counter() - start)
    if renderer is not None:
        renderer.close()
    return rate


def time_frames(env: DustEnv, cameras: list[str], frames: int = 50) -> dict[str, float]:
    """Median milliseconds per fast-mode frame of each camera, at the env's image size."""
    env.reset(seed=0)
    renderer = CameraRenderer(env.model, *env.image_shape[:2])
    times = {}
    for camera in cameras:
        renderer.render(env.data, camera)  # warm up (uploads, first draw)
        samples = []
        for _ in range(frames):
            start = time.perf_counter()
            renderer.render(env.data, camera)
            samples.append(time.perf_counter() - start)
        times[camera] = 1e3 * float(np.median(samples))
    renderer.close()
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="DustFranka-v0")
    parser.add_argument("--tasks", nargs="+", default=["pick_place"])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--repeats", type=int, default=3, help="best of N (the machine is noisy)")
    parser.add_argument("--all-cores", action="store_true", help="do not pin to one core")
    args = parser.parse_args()
    if not args.all_cores:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    import gymnasium as gym

    print("| env | task | mode | env steps/s | bare MuJoCo+mink steps/s | env / bare |")
    print("|---|---|---|---|---|---|")
    frame_rows = []
    for task in args.tasks:
        for mode in ("state", "rgb"):
            env = gym.make(args.env, task=task, obs_mode=mode).unwrapped
            steps = args.steps if mode == "state" else args.steps // 4
            actions = _actions(steps, env.action_space.shape[0])
            env_rate = max(time_env(env, actions) for _ in range(args.repeats))
            bare_rate = max(time_bare_loop(env, actions) for _ in range(args.repeats))
            label = "state" if mode == "state" else f"rgb {len(env.cameras)}x{env.image_shape[0]}px"
            print(f"| {args.env} | {task} | {label} | {env_rate:,.0f} | {bare_rate:,.0f} | "
                  f"{env_rate / bare_rate:.2f} |", flush=True)
            if mode == "rgb":
                all_cameras = [env.model.camera(i).name for i in range(env.model.ncam)]
                size = f"{env.image_shape[0]}x{env.image_shape[1]}"
                frame_rows += [f"| {args.env} | {task} | {camera} | {size} | {ms:.1f} |"
                               for camera, ms in time_frames(env, all_cameras).items()]
            env.close()
    print("\n| env | task | camera | pixels | ms per frame |\n|---|---|---|---|---|")
    print("\n".join(frame_rows))


if __name__ == "__main__":
    main()
