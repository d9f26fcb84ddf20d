"""The PyBullet bodies of the peeling scene and the per-task dynamics parameters (3.2, 3.2.1).

Geometry (engine units are SI: m, kg, s, N; x is the peel direction, z up):

* **pad**: a static box, top face at z = 0. Its ``lateralFriction`` (sliding friction),
  ``contactStiffness`` and ``contactDamping`` are the task's P_k values; friction and stiffness
  are scaled by the local adhesion factor of the ``tile_length`` patch under the blade (vacuum
  patches drawn per task), switched as the blade crosses patches.
* **blade**: a multibody with a fixed base and one prismatic joint along x. The robot holds the
  tool ``press_depth`` into the pad (section 2: pressed down from B on); the thin wedge blade and
  the wrist are a vertical spring (``tool_compliance_z_mm_per_n``), so the blade's actual
  indentation psi is the quasi-static equilibrium of that spring, the pad's soft contact and the
  vertical load of the glass on the blade (:meth:`set_blade_depth`, computed by the env every
  engine step): a heavier load presses the blade deeper and the pad's reaction, and with it the
  pad friction, grows. With zero compliance psi = ``press_depth`` (a rigid tool). The robot drives the
  blade through a compliance (tool + sensor): a spring-damper between the commanded carriage
  position and the blade, applied as the joint force. The blade's pad friction switches between
  the static (``static_friction_ratio`` x) and kinetic level with the blade's slip state, so
  stick-slip emerges from the engine's friction constraint.
* **substrate**: the peeled part of the glass, a multibody free to move along z only, riding on
  the blade's top face; a vacuum / peel-front load pulls it down on the blade (see env).

The sensor forces are the engine's contact forces on the blade (``getContactPoints``): normal and
both friction directions, summed over all contact points.
"""

from __future__ import annotations

import contextlib

from ._pybullet import pb
from .config import SimConfig

MM = 1e-3  # m per mm (engine length unit is the metre)


class Scene:
    """One PyBullet DIRECT client holding pad tiles, blade and substrate."""

    def __init__(self, cfg: SimConfig) -> None:
        self.cfg = cfg
        sc = cfg.scene
        self.client = pb.connect(pb.DIRECT)
        c = self.client
        self.dt_phys = cfg.task.dt_s / sc.substeps
        pb.setPhysicsEngineParameter(
            fixedTimeStep=self.dt_phys, numSubSteps=0, numSolverIterations=20,
            deterministicOverlappingPairs=1, physicsClientId=c,
        )
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        # --- pad: one static box, top face at z = 0, from x = -tile_length on. Its dynamics
        # are set to the local values of the tile under the blade (set_local), so the local
        # adhesion varies along the path without internal tile edges in the contact.
        tl = sc.tile_length_mm * MM
        self.tile_x0 = -tl  # x of the first tile's rear edge, m
        pad_len = sc.n_tiles * tl
        pshape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[pad_len / 2, 0.02, 0.5 * MM],
                                         physicsClientId=c)
        self._pad_x = self.tile_x0 + pad_len / 2
        self._pad_top = 0.0  # height of the pad's top face (moves with the indentation), m
        self.pad = pb.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=pshape,
            basePosition=[self.tile_x0 + pad_len / 2, 0.0, -0.5 * MM], physicsClientId=c,
        )
        self._pad_base = (1.0, 1.0, 1.0)
        self._local: float | None = None
        # --- blade: fixed base, prismatic joint along x, box link 1 mm thick
        bl = sc.blade_contact_length_mm * MM
        self.blade_half = [bl / 2, 0.005, sc.blade_thickness_mm * MM / 2]
        bshape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=self.blade_half,
                                         physicsClientId=c)
        # initial indentation: the tool spring's equilibrium on the pad at the simulator's mean
        # stiffness without load (= press_depth for a rigid tool); the env moves the blade to
        # the load's equilibrium every engine step (set_blade_depth)
        c_tool = sc.tool_compliance_z_mm_per_n * MM
        k_mean = 0.5 * (cfg.randomization.stiffness_low + cfg.randomization.stiffness_high)
        self.depth0 = sc.press_depth_mm * MM / (1.0 + c_tool * 4.0 * k_mean)
        z_blade = self.blade_half[2] - self.depth0
        self._depth: float | None = self.depth0  # current indentation psi, m
        self.blade = pb.createMultiBody(
            baseMass=0.0, basePosition=[0.0, 0.0, z_blade],
            linkMasses=[sc.blade_mass_kg], linkCollisionShapeIndices=[bshape],
            linkVisualShapeIndices=[-1], linkPositions=[[0, 0, 0]],
            linkOrientations=[[0, 0, 0, 1]], linkInertialFramePositions=[[0, 0, 0]],
            linkInertialFrameOrientations=[[0, 0, 0, 1]], linkParentIndices=[0],
            linkJointTypes=[pb.JOINT_PRISMATIC], linkJointAxis=[[1, 0, 0]],
            physicsClientId=c,
        )
        pb.setJointMotorControl2(self.blade, 0, pb.VELOCITY_CONTROL, force=0.0,
                                 physicsClientId=c)
        pb.changeDynamics(self.blade, 0, linearDamping=0.0, angularDamping=0.0,
                          jointDamping=0.0, physicsClientId=c)
        # --- substrate: fixed base above the blade, prismatic joint along z
        sshape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[0.03, 0.004, 0.25 * MM],
                                         physicsClientId=c)
        self.z_sub0 = z_blade + self.blade_half[2] + 0.25 * MM  # resting height of its centre
        self.substrate = pb.createMultiBody(
            baseMass=0.0, basePosition=[0.02, 0.0, self.z_sub0],
            linkMasses=[sc.substrate_mass_kg], linkCollisionShapeIndices=[sshape],
            linkVisualShapeIndices=[-1], linkPositions=[[0, 0, 0]],
            linkOrientations=[[0, 0, 0, 1]], linkInertialFramePositions=[[0, 0, 0]],
            linkInertialFrameOrientations=[[0, 0, 0, 1]], linkParentIndices=[0],
            linkJointTypes=[pb.JOINT_PRISMATIC], linkJointAxis=[[0, 0, 1]],
            physicsClientId=c,
        )
        pb.setJointMotorControl2(self.substrate, 0, pb.VELOCITY_CONTROL, force=0.0,
                                 physicsClientId=c)
        pb.changeDynamics(self.substrate, 0, lateralFriction=sc.glass_friction,
                          contactStiffness=sc.substrate_contact_stiffness,
                          contactDamping=sc.substrate_contact_damping,
                          linearDamping=0.0, jointDamping=0.0, physicsClientId=c)
        pb.setCollisionFilterPair(self.substrate, self.pad, 0, -1, 0, physicsClientId=c)
        self.kinetic_friction = 1.0
        self._blade_mu = None
        self.set_blade_friction(1.0)
        self._state_id: int | None = None
        self._saved_depth: dict[int, tuple[float | None, float]] = {}

    # ----------------------------------------------------------------------------- params
    def apply_params(self, friction: float, stiffness: float, damping: float) -> None:
        """Set the task's P_k (pad friction, contact stiffness N/m, contact damping N s/m)."""
        self._pad_base = (friction, stiffness, damping)
        self._local = None

    def set_local(self, factor: float) -> None:
        """Local adhesion factor of the tile under the blade: scales the pad's friction and
        contact stiffness (a stronger vacuum patch presses the pad harder onto the blade)."""
        if factor != self._local:
            mu, k, c = self._pad_base
            pb.changeDynamics(self.pad, -1, lateralFriction=mu * factor,
                              contactStiffness=k * factor, contactDamping=c,
                              physicsClientId=self.client)
            self._local = factor

    def set_blade_friction(self, mu: float) -> None:
        """Blade friction factor (multiplies the tile's: Bullet combines friction as a product)."""
        if mu != self._blade_mu:
            pb.changeDynamics(self.blade, 0, lateralFriction=mu, physicsClientId=self.client)
            self._blade_mu = mu

    def set_blade_depth(self, psi_m: float) -> None:
        """Set the blade's indentation into the pad to ``psi_m`` (m). The blade and the glass
        riding on it keep their heights; the static pad body is placed so that its top face is
        ``psi_m`` above the blade's underside (the same relative geometry, without moving the
        bodies the blade-glass contact lives on)."""
        if psi_m != self._depth:
            self._pad_top = psi_m - self.depth0
            pb.resetBasePositionAndOrientation(
                self.pad, [self._pad_x, 0.0, -0.5 * MM + self._pad_top], [0.0, 0.0, 0.0, 1.0],
                physicsClientId=self.client)
            self._depth = psi_m

    # ----------------------------------------------------------------------------- state
    def reset_bodies(self) -> None:
        """Blade at x = 0 (point C), substrate resting on it, all at rest."""
        c = self.client
        pb.resetJointState(self.blade, 0, 0.0, 0.0, physicsClientId=c)
        pb.resetJointState(self.substrate, 0, 0.0, 0.0, physicsClientId=c)

    def blade_state(self) -> tuple[float, float]:
        """Blade (x in m, xdot in m/s)."""
        s = pb.getJointState(self.blade, 0, physicsClientId=self.client)
        return s[0], s[1]

    def substrate_lift(self) -> float:
        """Height of the substrate's underside above the pad top, m."""
        z = pb.getJointState(self.substrate, 0, physicsClientId=self.client)[0]
        return self.z_sub0 + z - 0.25 * MM - self._pad_top

    def save(self) -> int:
        sid = pb.saveState(physicsClientId=self.client)
        self._saved_depth[sid] = (self._depth, self._pad_top)
        return sid

    def restore(self, state_id: int) -> None:
        """Restore a saved engine state (the pad's pose with it, so psi's cache too)."""
        pb.restoreState(stateId=state_id, physicsClientId=self.client)
        self._depth, self._pad_top = self._saved_depth[state_id]

    def remove_state(self, state_id: int) -> None:
        pb.removeState(state_id, physicsClientId=self.client)
        self._saved_depth.pop(state_id, None)

    # ----------------------------------------------------------------------------- physics
    def substep(self, blade_force: float, substrate_force: float) -> None:
        """One engine step with the coupling force on the blade joint (N, +x) and the
        vacuum / peel load on the substrate joint (N, +z)."""
        c = self.client
        pb.setJointMotorControl2(self.blade, 0, pb.TORQUE_CONTROL, force=blade_force,
                                 physicsClientId=c)
        pb.setJointMotorControl2(self.substrate, 0, pb.TORQUE_CONTROL, force=substrate_force,
                                 physicsClientId=c)
        pb.stepSimulation(physicsClientId=c)

    def contact_forces(self) -> tuple[float, float, float, float]:
        """Engine contact forces on the blade after the last step.

        Returns (fx_resist, fz_load, fz_pad, penetration_m): fx_resist is minus the x-sum of all
        contact forces on the blade (positive opposes forward motion), fz_load the downward
        force of the substrate on the blade, fz_pad the pad's upward reaction, and the largest
        pad penetration (m)."""
        fx = 0.0
        fz_load = 0.0
        fz_pad = 0.0
        pen = 0.0
        for cp in pb.getContactPoints(bodyA=self.blade, physicsClientId=self.client):
            # cp: 5 posOnA... 7 normal (from B to A), 8 distance, 9 normalForce,
            # 10 lateralFriction1, 11 lateralFrictionDir1, 12 lateralFriction2, 13 dir2
            n = cp[7]
            fn = cp[9]
            f1, d1, f2, d2 = cp[10], cp[11], cp[12], cp[13]
            # force on A (blade) = fn * normal(B->A) + friction (Bullet reports the friction
            # impulse direction applied to A)
            fxa = fn * n[0] + f1 * d1[0] + f2 * d2[0]
            fza = fn * n[2] + f1 * d1[2] + f2 * d2[2]
            fx -= fxa
            if cp[2] == self.substrate:
                fz_load -= fza
            else:
                fz_pad += fza
                pen = max(pen, -cp[8])
        return fx, fz_load, fz_pad, pen

    def load_and_penetration(self) -> tuple[float, float]:
        """The two contact read-outs the environment records, from one ``getContactPoints``:
        the downward force of the substrate on the blade (N) and the largest pad penetration
        (m). Same arithmetic and order as :meth:`contact_forces`, without the unused sums."""
        fz_load = 0.0
        pen = 0.0
        sub = self.substrate
        for cp in pb.getContactPoints(self.blade, physicsClientId=self.client):
            if cp[2] == sub:
                fz_load -= cp[9] * cp[7][2] + cp[10] * cp[11][2] + cp[12] * cp[13][2]
            elif -cp[8] > pen:
                pen = -cp[8]
        return fz_load, pen

    def close(self) -> None:
        if self.client is not None and self.client >= 0:
            with contextlib.suppress(pb.error):
                pb.disconnect(physicsClientId=self.client)
            self.client = -1
