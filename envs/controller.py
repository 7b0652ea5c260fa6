"""Operational-space control through differential inverse kinematics (mink).

The policy commands end-effector poses; every control step this controller
moves each mink ``FrameTask`` target, solves one QP (``mink.solve_ik``) under
joint-position and joint-velocity limits (and, where the robot asks for it,
collision avoidance between named geoms) with a ``PostureTask`` regulariser,
and integrates the result into joint position targets for the actuators.

Each step starts from the measured joint positions, so the controller holds
no hidden state: the observation is the whole story (robots are
gravity-compensated, as real arms are, so a zero action holds still).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import mink
import mujoco
import numpy as np


class OperationalSpaceController:
    """Differential-IK end-effector controller for one or more frames.

    Args:
        model: kinematic model containing the robot (no free objects).
        sites: names of the end-effector sites, one FrameTask each.
        home_qpos: joint name -> posture target.
        max_joint_velocity: joint name -> velocity limit (rad/s).
        dt: control period (s); the QP's integration step.
        solver: a QP solver known to ``qpsolvers`` (``"daqp"`` or ``"quadprog"``).
        position_cost: FrameTask position weight.
        orientation_cost: FrameTask orientation weight.
        posture_cost: PostureTask weight; small, so it resolves redundancy without
            pulling the end effector off its target (1e-2 drifts ~0.4 mm per step).
        joint_posture_costs: joint name -> PostureTask weight overriding ``posture_cost``
            (a stiffer waist lets the arms do the reaching and moves the waist only when needed).
        collision_pairs: pairs of geom-name groups kept apart by a
            ``mink.CollisionAvoidanceLimit``; empty for none.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        sites: Sequence[str],
        home_qpos: Mapping[str, float],
        max_joint_velocity: Mapping[str, float],
        dt: float,
        solver: str = "daqp",
        position_cost: float = 1.0,
        orientation_cost: float = 0.5,
        posture_cost: float = 1e-3,
        joint_posture_costs: Mapping[str, float] | None = None,
        collision_pairs: Sequence[tuple[Sequence[str], Sequence[str]]] = (),
    ) -> None:
        self.model = model
        self.dt = dt
        self.solver = solver
        self.configuration = mink.Configuration(model)
        self.frame_tasks = [
            mink.FrameTask(site, "site", position_cost=position_cost, orientation_cost=orientation_cost,
                           lm_damping=1e-3)
            for site in sites
        ]
        self.home = self.configuration.q.copy()
        for joint, value in home_qpos.items():
            self.home[model.joint(joint).qposadr[0]] = value
        cost = np.full(model.nv, posture_cost)
        for joint, value in (joint_posture_costs or {}).items():
            cost[model.joint(joint).dofadr[0]] = value
        self.posture_task = mink.PostureTask(model, cost=cost)
        self.posture_task.set_target(self.home)
        self.limits = [mink.ConfigurationLimit(model), mink.VelocityLimit(model, dict(max_joint_velocity))]
        if collision_pairs:
            pairs = [(list(a), list(b)) for a, b in collision_pairs]
            self.limits.append(mink.CollisionAvoidanceLimit(model, pairs))
        self._tasks = [*self.frame_tasks, self.posture_task]

    def step(self, q: np.ndarray, targets: Sequence[mink.SE3], dt: float | None = None) -> np.ndarray:
        """From joint positions ``q``, move toward ``targets`` for one control period (or ``dt`` seconds: the
        velocity limits then allow that much motion).

        Returns:
            Commanded joint positions (the kinematic model's full ``qpos``).

        Raises:
            mink.NoSolutionFound: the QP is infeasible (the caller truncates the episode).
        """
        self.configuration.update(q)
        for task, target in zip(self.frame_tasks, targets, strict=True):
            task.set_target(target)
        dt = self.dt if dt is None else dt
        velocity = mink.solve_ik(self.configuration, self._tasks, dt, self.solver, damping=1e-3, limits=self.limits)
        self.configuration.integrate_inplace(velocity, dt)
        return self.configuration.q
