"""``DustEnv``: a seeded, language-conditioned tabletop manipulation env.

The policy commands end-effector poses (delta or absolute) and gripper
closures; an operational-space controller (mink) turns them into joint
targets for the robot's position actuators at the control rate while
MuJoCo steps physics at the physics rate. Observations use the flat
LeRobot-style names of the torchrl VLA schema (``observation.image.<cam>``,
``observation.state``, ``language_instruction``); ``dust_rl.envs.torchrl_env``
nests them into the canonical TensorDict keys. The numeric-only state mode
names its arrays without dots (:data:`STATE_MODE_KEYS`), because RL
libraries key torch modules by observation name and torch rejects dots there.
"""

from __future__ import annotations

import copy
import dataclasses
import string
from collections.abc import Sequence

import gymnasium as gym
import mink
import mujoco  # MUJOCO_GL is set before this by the package's __init__ (envs/__init__.py)
import numpy as np
import qpsolvers

from dust_rl.keys import ENV_STATE_KEY, INSTRUCTION_KEY, STATE_KEY, flat_name

from . import arguments
from .controller import OperationalSpaceController
from .experts import WaypointExpert
from .instruction_space import MAX_INSTRUCTION_LENGTH, InstructionText, encode_instruction, instruction_bytes_space
from .rendering import RENDER_QUALITIES, CameraRenderer
from .robot import RobotConfig
from .robots import ROBOT_BUILDERS
from .scene import new_tabletop_spec
from .tasks import make_task

OBS_MODES = ("rgb", "state")
CONTROL_MODES = ("delta", "absolute")
REWARD_TYPES = ("sparse", "dense")
TEXT_FORMATS = ("str", "utf8")
INSTRUCTION_CHARSET = string.ascii_letters + string.digits + " ,.'-"
# Flat VLA names of the numeric observations (torchrl_env nests them at the dots).
FLAT_STATE_KEY = flat_name(STATE_KEY)
FLAT_ENV_STATE_KEY = flat_name(ENV_STATE_KEY)
# obs_mode="state" names: SB3's MultiInputPolicy keys an nn.ModuleDict by them, which rejects dots.
# They are LeRobot's gym-env names (gym_aloha, gym_pusht); torchrl's GymEnv would rename a plain "state".
STATE_MODE_KEYS = {FLAT_STATE_KEY: "agent_pos", FLAT_ENV_STATE_KEY: "environment_state"}

MAX_TRANSLATION = 0.02  # metres per control step at |action| = 1 (delta mode)
MAX_ROTATION = 0.1  # radians per control step at |action| = 1 (delta mode)
# place_end_effectors: 10 IK steps of 4 control periods each put 90% of 100 walk and close-up targets (up to ~50 cm
# from home) within 0.01 mm and the farthest 3.2 mm off (5 steps left 20 mm at the 90th percentile), then 2 control
# periods of physics (the fingers' command about half reached).
PLACEMENT_ITERATIONS = 10
PLACEMENT_STEP_PERIODS = 4
PLACEMENT_SETTLE_STEPS = 2
ACTION_WIDTH = 7  # numbers per end effector: translation (3), rotation (3), closure (1)
ACTION_PARTS = ("x", "y", "z", "rx", "ry", "rz", "closure")  # names of those ACTION_WIDTH numbers
STATE_PARTS = ("x", "y", "z", "qw", "qx", "qy", "qz", "opening")  # per end effector, after the joints
CLOSURE = 6  # index of the closure within an end effector's numbers
# Position targets may dip this far below the robot's workspace box (to press on the table).
_TARGET_BELOW_WORKSPACE = np.array([0.0, 0.0, 0.05])
_INSTABILITY_WARNINGS = np.array([mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                                  mujoco.mjtWarning.mjWARN_BADQACC], dtype=int)


@dataclasses.dataclass(frozen=True)
class SimSnapshot:
    """A copy of what `DustEnv.step()` changes (`DustEnv.snapshot()`)."""

    data: mujoco.MjData
    elapsed: int
    progress: float


def environment_state_names(width: int) -> list[str]:
    """Names of ``width`` privileged-state entries: their layout is the task's (see its ``environment_state``)."""
    return [f"environment_state_{i}" for i in range(width)]


class DustEnv(gym.Env):
    """Tabletop manipulation with end-effector control through mink.

    Args:
        task: task name; see :func:`dust_rl.envs.list_tasks`.
        robot: robot suite (``"franka"``, ``"humanoid"``).
        obs_mode: ``"rgb"`` (camera images, state, instruction) or ``"state"`` (numeric
            arrays only, no rendering, keys ``"agent_pos"`` and ``"environment_state"``: what RL
            baselines such as SB3 accept; the instruction is then in ``info["language_instruction"]``).
        control_mode: ``"delta"`` (default; per step at most 2 cm and 0.1 rad) or
            ``"absolute"`` (pose in the robot's workspace box, axis-angle / pi).
        image_size: image height and width in pixels (a positive int or ``(height, width)``).
        cameras: cameras to render; defaults to the robot's (Franka: ``front``, ``wrist``;
            humanoid: ``head``, with ``left_wrist``, ``right_wrist`` and ``front`` on request).
        reward_type: ``"sparse"`` (1 on success) or ``"dense"`` (the sparse reward plus potential-based
            shaping by the task's staged :meth:`progress`; see :meth:`step`).
        shaping_discount: the per-step discount of the agent the dense reward is shaped for (``gamma``: SB3's
            default 0.99); its optimal policies are then the sparse reward's.
        render_mode: ``"rgb_array"`` or None.
        render_quality: ``"fast"`` (no shadows/MSAA, low-poly robot) or ``"visual"``.
        max_episode_steps: overrides the task's default time limit (a positive int).
        control_hz: control rate; physics runs at ``1 / physics_dt``.
        physics_dt: MuJoCo timestep (s); must divide the control period into whole substeps.
        ik_solver: QP solver for mink, one of ``qpsolvers.available_solvers`` (``"daqp"``, ``"quadprog"``).
        privileged_state: append the task's ``environment_state`` (object positions) to
            ``observation.state``. A policy trained on it cannot fail for lack of seeing the
            objects: an oracle that measures how much perception costs, not a deployable policy.
        privileged_noise: standard deviation (m) of a Gaussian offset added to that appended state, drawn once
            per episode from its seed: the oracle of a perception that misplaces every object by about
            this much, consistently, to measure how precise a read-out must be. Needs ``privileged_state``.
        text_format: ``"str"`` (default), or ``"utf8"``: every string the env gives (the instruction, in the
            observation and in ``info``; ``info["task"]``, ``info["truncation_reason"]``) as zero-padded UTF-8
            bytes, uint8 ``[1024]`` (:func:`~dust_rl.envs.instruction_space.decode_instruction` reads one back),
            which torchrl's batched ``GymEnv(..., num_envs=N)`` can stack; strings it cannot.

    Raises:
        ValueError: an argument is out of its domain; the message names it and what is allowed.

    The action has 7 numbers per end effector, in the robot's end-effector order
    (humanoid: left hand, then right hand): translation (3), rotation as a
    world-frame axis-angle (3), closure (1; -1 open, 1 closed; a hand closes
    through its grasp synergy). Actions outside [-1, 1] are clipped; non-finite
    or wrongly shaped actions raise ``ValueError``. An infeasible IK problem or
    diverging physics ends the episode with ``truncated=True`` and
    ``info["truncation_reason"]`` set.

    A pickle holds the constructor's arguments and the RNG, not the simulator (:meth:`__getstate__`);
    ``copy.deepcopy`` copies the whole state (:meth:`__deepcopy__`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(
        self,
        task: str = "pick_place",
        robot: str = "franka",
        obs_mode: str = "rgb",
        control_mode: str = "delta",
        image_size: int | Sequence[int] = 128,
        cameras: Sequence[str] | None = None,
        reward_type: str = "sparse",
        shaping_discount: float = 0.99,
        render_mode: str | None = None,
        render_quality: str = "fast",
        max_episode_steps: int | None = None,
        control_hz: float = 20.0,
        physics_dt: float = 0.002,
        ik_solver: str = "daqp",
        privileged_state: bool = False,
        privileged_noise: float = 0.0,
        text_format: str = "str",
    ) -> None:
        self._arguments = {name: value for name, value in locals().items() if name != "self"}  # for __getstate__
        arguments.check_choice("obs_mode", obs_mode, OBS_MODES)
        arguments.check_choice("control_mode", control_mode, CONTROL_MODES)
        arguments.check_choice("reward_type", reward_type, REWARD_TYPES)
        arguments.check_choice("text_format", text_format, TEXT_FORMATS)
        self._text = encode_instruction if text_format == "utf8" else str
        self.instruction_space = (instruction_bytes_space() if text_format == "utf8" else
                                  InstructionText(MAX_INSTRUCTION_LENGTH, min_length=1, charset=INSTRUCTION_CHARSET))
        self.shaping_discount = arguments.discount("shaping_discount", shaping_discount)
        arguments.check_choice("render_mode", render_mode, (None, *self.metadata["render_modes"]))
        arguments.check_choice("render_quality", render_quality, RENDER_QUALITIES)
        arguments.check_choice("robot", robot, tuple(ROBOT_BUILDERS))
        arguments.check_choice("ik_solver", ik_solver, qpsolvers.available_solvers)
        self.image_shape = arguments.image_shape(image_size)
        self.n_substeps = arguments.substeps(control_hz, physics_dt)
        max_episode_steps = arguments.max_episode_steps(max_episode_steps)
        self.privileged_state = arguments.flag("privileged_state", privileged_state)
        self.privileged_noise = arguments.non_negative("privileged_noise", privileged_noise)
        if self.privileged_noise and not self.privileged_state:
            raise ValueError("privileged_noise needs privileged_state=True: it perturbs that appended state")
        self.task = make_task(task, robot)
        self._privileged_offset = np.zeros(self.task.environment_state_dim, np.float32)
        self.obs_mode, self.control_mode, self.reward_type = obs_mode, control_mode, reward_type
        self.render_mode = render_mode
        self.max_episode_steps = self.task.max_episode_steps if max_episode_steps is None else max_episode_steps
        self.control_dt = self.n_substeps * physics_dt
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.control_dt))}

        self.model, self.robot = self._compile(physics_dt, with_task=True)
        self.data = mujoco.MjData(self.model)
        self.task.bind(self.model, self.robot)
        ik_model, _ = self._compile(physics_dt, with_task=False)
        self.controller = OperationalSpaceController(
            ik_model, [ee.site for ee in self.robot.end_effectors], self.robot.home_qpos,
            self.robot.max_joint_velocity, self.control_dt, solver=ik_solver,
            joint_posture_costs=self.robot.posture_costs, collision_pairs=self.robot.collision_pairs)
        self._index_robot(ik_model)

        self.cameras = (self.robot.default_cameras if cameras is None
                        else arguments.camera_names(cameras, self._camera_names()))
        self._renderer: CameraRenderer | None = None
        self._render_quality = render_quality

        n_ee = len(self.robot.end_effectors)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_WIDTH * n_ee,), np.float32)
        self.observation_space = self._make_observation_space()
        self._instruction = ""
        self._elapsed = 0
        self._progress = 0.0  # of the newest state (the dense reward's potential)

    # -- construction ---------------------------------------------------------------------------

    def _compile(self, physics_dt: float, with_task: bool) -> tuple[mujoco.MjModel, RobotConfig]:
        spec = new_tabletop_spec(physics_dt)
        robot = ROBOT_BUILDERS[self.task.robot](spec)
        if with_task:
            self.task.build(spec)
        return spec.compile(), robot

    def _index_robot(self, ik_model: mujoco.MjModel) -> None:
        """Cache the index maps between the simulator, the IK model and the actuators."""
        ik_joints = [ik_model.joint(j).name for j in range(ik_model.njnt)]
        self._sim_qadr = np.array([self.model.joint(j).qposadr[0] for j in ik_joints])
        # Joint bounds for clipping the IK start (hinge/slide joints: one qpos each).
        limited = ik_model.jnt_limited.astype(bool)
        self._ik_low = np.where(limited, ik_model.jnt_range[:, 0] + 1e-6, -np.inf)
        self._ik_high = np.where(limited, ik_model.jnt_range[:, 1] - 1e-6, np.inf)
        self._ik_arm_qadr = np.array([ik_model.joint(j).qposadr[0] for j in self.robot.arm_joints])
        self._arm_ctrl = np.array([self.model.actuator(a).id for a in self.robot.arm_actuators])
        self._ee_sites = np.array([self.model.site(ee.site).id for ee in self.robot.end_effectors])
        self._ee_ctrl = [np.array([self.model.actuator(a).id for a in ee.actuators])
                         for ee in self.robot.end_effectors]
        self._ee_opening = [np.array([self.model.joint(j).qposadr[0] for j in ee.opening_joints])
                            for ee in self.robot.end_effectors]
        self._workspace_low, self._workspace_high = (np.asarray(corner, float) for corner in self.robot.workspace)
        self._state_joints = [*self.robot.arm_joints,
                              *(j for ee in self.robot.end_effectors for j in ee.opening_joints)]
        self._state_qadr = np.array([self.model.joint(j).qposadr[0] for j in self._state_joints])
        self._home_qpos = {self.model.joint(j).qposadr[0]: v for j, v in self.robot.home_qpos.items()}

    def _camera_names(self) -> list[str]:
        return [self.model.camera(i).name for i in range(self.model.ncam)]

    def _make_observation_space(self) -> gym.spaces.Dict:
        n_ee = len(self.robot.end_effectors)
        state_dim = len(self._state_qadr) + len(STATE_PARTS) * n_ee  # joints + per-EE (pos, quat, opening)
        state_dim += self.task.environment_state_dim if self.privileged_state else 0
        spaces: dict[str, gym.spaces.Space] = {}
        if self.obs_mode == "rgb":
            for camera in self.cameras:
                spaces[f"observation.image.{camera}"] = gym.spaces.Box(0, 255, self.image_shape, np.uint8)
        spaces[FLAT_STATE_KEY] = gym.spaces.Box(-np.inf, np.inf, (state_dim,), np.float32)
        spaces[FLAT_ENV_STATE_KEY] = gym.spaces.Box(-np.inf, np.inf, (self.task.environment_state_dim,), np.float32)
        if self.obs_mode == "rgb":
            spaces[INSTRUCTION_KEY] = self.instruction_space
        return gym.spaces.Dict(self._mode_keys(spaces))

    # -- gymnasium API ---------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        self.reset_unobserved(seed=seed, options=options)
        return self.observe(), self._info(success=False, reason="")

    def reset_unobserved(self, *, seed: int | None = None, options: dict | None = None) -> None:
        """:meth:`reset` without its observation (nothing rendered), for callers that move the arm before they
        look (``dust_rl.train.readout.aux_frames`` places it, then renders one frame): the two frames of a
        reset are ~70% of its 4 ms on a 2-core x86 CPU."""
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        for adr, value in self._home_qpos.items():
            self.data.qpos[adr] = value
        self.data.ctrl[self._arm_ctrl] = [self.robot.home_qpos[j] for j in self.robot.arm_joints]
        for ee, ctrl in zip(self.robot.end_effectors, self._ee_ctrl):
            self.data.ctrl[ctrl] = ee.closure_to_ctrl(0.0)
        self._instruction = self.task.reset(self.model, self.data, self.np_random)
        if self.privileged_noise:  # drawn after the task's draws, which stay as they were
            self._privileged_offset = self.np_random.normal(0.0, self.privileged_noise,
                                                            self.task.environment_state_dim).astype(np.float32)
        mujoco.mj_forward(self.model, self.data)
        # Let props settle on the table before the first observation.
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        self._elapsed = 0
        if self.reward_type == "dense":
            self._progress = self.progress()

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        """One control step. The dense reward is the sparse one plus potential-based shaping (Ng, Harada and
        Russell 1999): gamma * progress(s') - progress(s) with ``gamma = shaping_discount`` and progress 0 once
        the episode has ended in success, so success pays 1 - progress(s), an episode's discounted rewards sum to
        its discounted sparse return minus the start's progress, and an agent with that discount has the sparse
        reward's optimal policies. Two earlier forms were exploitable: paying the progress itself each step made
        hovering short of success worth up to ~100 times its progress; paying its undiscounted change
        (gamma = 1 for an agent with gamma < 1) made lifting a cube and dropping it again pay (the lift is
        counted at full value, the loss discounted)."""
        reward, terminated, truncated, info = self.step_unobserved(action)
        return self.observe(), reward, terminated, truncated, info

    def step_unobserved(self, action: np.ndarray) -> tuple[float, bool, bool, dict]:
        """:meth:`step` without its observation (nothing rendered): its reward, terminated, truncated and info, for
        callers that execute several actions before they look (noise steering executes a chunk, then observes
        with :meth:`observe`)."""
        success, reason = self.advance(action)
        if self.reward_type == "dense":
            progress = self.progress()
            reward = (1.0 if success else self.shaping_discount * progress) - self._progress
            self._progress = progress
        else:
            reward = float(success)
        return float(reward), success, bool(reason), self._info(success, reason)

    def snapshot(self) -> SimSnapshot:
        """The state a step changes (the simulator's data, the step count, the shaping's progress), for
        :meth:`restore`: a lookahead search tries motions and comes back. The controller
        and the task keep no state between steps (both read the simulator's)."""
        data = mujoco.MjData(self.model)
        mujoco.mj_copyData(data, self.model, self.data)
        return SimSnapshot(data, self._elapsed, self._progress)

    def restore(self, snapshot: SimSnapshot) -> None:
        """Back to ``snapshot``: the next steps are those that would have followed it, bit for bit."""
        mujoco.mj_copyData(self.data, self.model, snapshot.data)
        self._elapsed, self._progress = snapshot.elapsed, snapshot.progress

    def progress(self) -> float:
        """The task's staged progress toward success, in [0, 1): the potential of the dense reward."""
        return float(self.task.progress(self.model, self.data, self.data.site_xpos[self._ee_sites[0]]))

    def advance(self, action: np.ndarray) -> tuple[bool, str]:
        """One control step without an observation (no rendering): :meth:`step` minus the observation, for
        callers that only look at the end of a motion (``dust_rl.train.readout.aux_frames`` renders one frame after many
        steps). Returns (success, the truncation reason or "")."""
        action = self._validate_action(action)
        reason = self._apply_action(action)
        if not reason:
            reason = self._simulate()
        self._elapsed += 1
        success = not reason and self.task.is_success(self.model, self.data)
        if not reason and self._elapsed >= self.max_episode_steps:
            reason = "time_limit"
        return bool(success), reason

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self._render_camera(self.robot.default_cameras[0])

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- internals -------------------------------------------------------------------------------

    def _validate_action(self, action: np.ndarray) -> np.ndarray:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action has shape {action.shape}; expected {self.action_space.shape}")
        if not np.isfinite(action).all():
            raise ValueError(f"action contains NaN or infinite values: {action}")
        return np.minimum(np.maximum(action, -1.0), 1.0)

    def _apply_action(self, action: np.ndarray) -> str:
        """Solve IK for the commanded poses and write actuator controls; returns a failure reason or ''."""
        targets = []
        for i, site in enumerate(self._ee_sites):
            a = action[ACTION_WIDTH * i: ACTION_WIDTH * (i + 1)]
            pose = np.empty(7)  # mink's wxyz_xyz layout
            if self.control_mode == "delta":
                current = np.empty(4)
                mujoco.mju_mat2Quat(current, self.data.site_xmat[site])
                mujoco.mju_mulQuat(pose[:4], axis_angle_to_quat(a[3:6] * MAX_ROTATION), current)
                pose[4:] = self.data.site_xpos[site] + a[:3] * MAX_TRANSLATION
            else:
                pose[:4] = axis_angle_to_quat(a[3:6] * np.pi)
                pose[4:] = self._workspace_low + (a[:3] + 1.0) / 2.0 * (self._workspace_high - self._workspace_low)
            pose[4:] = self._clip_to_workspace(pose[4:])
            targets.append(mink.SE3(pose))
        try:
            q_cmd = self.controller.step(self._ik_start(), targets)
        except mink.NoSolutionFound:
            return "ik_failure"
        self.data.ctrl[self._arm_ctrl] = q_cmd[self._ik_arm_qadr]
        for i, (ee, ctrl) in enumerate(zip(self.robot.end_effectors, self._ee_ctrl)):
            self.data.ctrl[ctrl] = ee.closure_to_ctrl((action[ACTION_WIDTH * i + CLOSURE] + 1.0) / 2.0)
        return ""

    def _ik_start(self) -> np.ndarray:
        """The measured joints as the IK's start, inside their limits: contacts can push joints marginally past
        them, which makes the QP infeasible."""
        return np.minimum(np.maximum(self.data.qpos[self._sim_qadr], self._ik_low), self._ik_high)

    def _clip_to_workspace(self, position: np.ndarray) -> np.ndarray:
        """A commanded position inside the robot's workspace (a little below its floor allowed, to press)."""
        return np.minimum(np.maximum(position, self._workspace_low - _TARGET_BELOW_WORKSPACE), self._workspace_high)

    def _simulate(self) -> str:
        """Step physics for one control period; returns 'physics_unstable' on divergence."""
        before = self._instability_warnings()
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        # MuJoCo resets the state silently when it diverges; its warning counters tell.
        if self._instability_warnings() != before or not np.all(np.isfinite(self.data.qpos)):
            return "physics_unstable"
        return ""

    def _instability_warnings(self) -> int:
        return int(self.data.warning.number[_INSTABILITY_WARNINGS].sum())

    def observe(self) -> dict:
        """The observation of the current state, as :meth:`step` returns it."""
        obs: dict = {}
        if self.obs_mode == "rgb":
            for camera in self.cameras:
                obs[f"observation.image.{camera}"] = self._render_camera(camera)
        env_state = self.task.environment_state(self.data).astype(np.float32)
        state = self._state()
        if self.privileged_state:
            state = np.concatenate([state, env_state + self._privileged_offset if self.privileged_noise else env_state])
        obs[FLAT_STATE_KEY] = state
        obs[FLAT_ENV_STATE_KEY] = env_state
        if self.obs_mode == "rgb":
            obs[INSTRUCTION_KEY] = self._text(self._instruction)
        return self._mode_keys(obs)

    def _mode_keys(self, entries: dict) -> dict:
        """State mode's dot-free names (:data:`STATE_MODE_KEYS`); rgb mode keeps the flat VLA names."""
        return {STATE_MODE_KEYS[k]: v for k, v in entries.items()} if self.obs_mode == "state" else entries

    def _state(self) -> np.ndarray:
        """Joint positions, then per end effector: position, quaternion (wxyz), opening."""
        n = len(self._state_qadr)
        state = np.empty(n + 8 * len(self._ee_sites))
        state[:n] = self.data.qpos[self._state_qadr]
        for i, (ee, site, opening) in enumerate(zip(self.robot.end_effectors, self._ee_sites, self._ee_opening)):
            block = state[n + 8 * i: n + 8 * i + 8]
            block[:3] = self.data.site_xpos[site]
            mujoco.mju_mat2Quat(block[3:7], self.data.site_xmat[site])
            block[7] = ee.opening(self.data.qpos[opening])
        return state.astype(np.float32)

    def state_names(self) -> list[str]:
        """A name per ``observation.state`` entry, in :meth:`_state`'s order (then the appended privileged state):
        what a LeRobot export lists as the feature's ``names``."""
        ends = [f"{ee.site}.{part}" for ee in self.robot.end_effectors for part in STATE_PARTS]
        privileged = environment_state_names(self.task.environment_state_dim) if self.privileged_state else []
        return [*self._state_joints, *ends, *privileged]

    def action_names(self) -> list[str]:
        """A name per action entry: :data:`ACTION_PARTS` of each end effector, named by its site."""
        return [f"{ee.site}.{part}" for ee in self.robot.end_effectors for part in ACTION_PARTS]

    def _render_camera(self, camera: str) -> np.ndarray:
        if self._renderer is None:
            self._renderer = CameraRenderer(self.model, self.image_shape[0], self.image_shape[1],
                                            self._render_quality)
        return self._renderer.render(self.data, camera)

    def _info(self, success: bool, reason: str) -> dict:
        """Step info; the flag a 0-d bool array: torchrl's ``default_info_dict_reader`` needs a ``dtype``, and
        gymnasium's vector envs stack arrays by their dtype (a ``np.bool_`` scalar into an object array)."""
        return {"is_success": np.array(success), "task": self._text(self.task.name),
                "truncation_reason": self._text(reason), INSTRUCTION_KEY: self._text(self._instruction)}

    # -- copies ----------------------------------------------------------------------------------

    def __getstate__(self) -> dict:
        """The constructor's arguments, the RNG and the registry spec: the simulator (MjModel, MjData, the
        controller's model: ~140 MB) is rebuilt on unpickling, so vector envs and worker processes ship no
        megabytes. An unpickled env starts before its first reset, as a new one does."""
        return {"arguments": self._arguments, "spec": self.spec,
                "np_random": (self._np_random, self._np_random_seed)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state["arguments"])
        self.spec = state["spec"]
        self._np_random, self._np_random_seed = state["np_random"]

    def __deepcopy__(self, memo: dict) -> DustEnv:
        """A copy in the same state, mid-episode included; its renderer (a GL context, which cannot be copied)
        is made anew at its first frame."""
        copied = object.__new__(type(self))
        memo[id(self)] = copied
        for name, value in self.__dict__.items():
            setattr(copied, name, None if name == "_renderer" else copy.deepcopy(value, memo))
        return copied

    # -- helpers for scripted experts ------------------------------------------------------------

    def end_effector_pose(self, index: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Measured position and rotation matrix of end effector ``index``."""
        site = self._ee_sites[index]
        return self.data.site_xpos[site].copy(), self.data.site_xmat[site].reshape(3, 3).copy()

    def end_effector_poses(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Measured position and rotation matrix of every end effector, in action order."""
        return [self.end_effector_pose(i) for i in range(len(self._ee_sites))]

    def place_end_effectors(self, targets: Sequence[mink.SE3], closures: Sequence[float],
                            iterations: int = PLACEMENT_ITERATIONS, settle_steps: int = PLACEMENT_SETTLE_STEPS) -> None:
        """Move the arm to ``targets`` without a motion: ``iterations`` IK steps of the controller from the
        measured joints (so joint and collision limits hold), the joints set there at rest, then
        ``settle_steps`` control periods of physics holding them while the fingers go to ``closures`` and
        whatever the arm was put into is pushed aside. For frames that show the arm at chosen poses
        (``dust_rl.train.readout.aux_frames``) at a fraction of a walk's cost: 10 IK steps take ~1 ms where
        a 20-step walk takes 16 ms (each step an IK solve and 25 physics substeps; a 2-core x86 CPU). Targets
        out of reach are approached as far as the limits let; positions are clipped to the workspace, as
        actions' are."""
        if len(targets) != len(self._ee_sites) or len(closures) != len(self._ee_sites):
            raise ValueError(f"{len(targets)} targets and {len(closures)} closures for {len(self._ee_sites)} end "
                             "effectors; give one of each per end effector")
        targets = [mink.SE3.from_rotation_and_translation(target.rotation(), self._clip_to_workspace(
            target.translation())) for target in targets]
        q = self._ik_start()
        for _ in range(iterations):
            try:
                q = self.controller.step(q, targets, PLACEMENT_STEP_PERIODS * self.control_dt).copy()
            except mink.NoSolutionFound:
                break  # the last feasible joints stand
        self.data.qpos[self._sim_qadr] = q
        self.data.qvel[:] = 0.0
        self.data.ctrl[self._arm_ctrl] = q[self._ik_arm_qadr]
        for ee, ctrl, closure in zip(self.robot.end_effectors, self._ee_ctrl, closures):
            self.data.ctrl[ctrl] = ee.closure_to_ctrl(float(np.clip(closure, 0.0, 1.0)))
        mujoco.mj_forward(self.model, self.data)
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps * settle_steps)

    def make_expert(self) -> WaypointExpert:
        """The task's scripted expert, bound to this env's state (call after reset; ``act()`` each step)."""
        return WaypointExpert(lambda: self.task.expert_plan(self.model, self.data), self.robot.end_effectors,
                              self.end_effector_poses, MAX_TRANSLATION, MAX_ROTATION)


def axis_angle_to_quat(axis_angle: np.ndarray) -> np.ndarray:
    """The unit quaternion (wxyz) of a turn by ``|axis_angle|`` radians about its direction."""
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    mujoco.mju_quatIntegrate(quat, axis_angle, 1.0)
    return quat
