"""PeelEnv: one peeling task C -> D in PyBullet, sampled every 0.1 s (sections 2, 3.2, 4.1-4.2).

Per sample (dt = 0.1 s, ``scene.substeps`` engine steps):

1. effects (plant) are evaluated from the state at the start of the sample;
2. the robot carriage moves at its actual speed: the command u scattered by the actuator,
   v_r ~ N(u, Sigma) (Eq. 2), through the plant's actuator lag;
3. each engine step, the compliance pulls the blade towards the carriage; the blade's pad
   friction is static while it sticks and kinetic while it slides (stick-slip); the substrate is
   pulled onto the blade by the vacuum / peel-front load
   ``a(q) * (base + rate_gain * damping * v_ref * (v_peel / v_ref)^n)``, where ``v_peel`` is the blade speed relaxed
   with ``load.rate_tau_s`` and a(q) the local adhesion factor of the tile under the blade;
4. the engine's contact forces on the blade plus the compensation of Eq. 21-22 give the true
   (F_RX, F_RZ); the WEF-6A model adds bias, noise (and plant drift) and quantises.

The recorded position q is the robot carriage's (what the arm's encoders report, as on the real
Nachi), so its velocity v scatters around the command (Eq. 2: v ~ N(u, Sigma)); the blade itself
lags behind by the compliance deflection and its stick-slip shows in the forces. The task ends at
q >= q_ter (``done``), on |F_RX| or |F_RZ| >= 20 N (``safety_stop``) or at
t >= t_max (``timeout``) (4.2). :meth:`rollout` replays the noise-free dynamics from saved
engine states for the planner's oracle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from . import compensation as comp
from ._pybullet import pb
from .config import SimConfig
from .effects import Effect, EffectAction, EffectState, combine
from .noise import ForceSensor
from .plant import SOURCES, PlantSpec, source_spec
from .scene import MM, Scene

_NO_ACTION = EffectAction()

#: Contact points of the blade-pad box manifold; each carries ``stiffness * psi`` (3.2.1).
PAD_CONTACT_POINTS = 4

#: Physical parameters that define one task (P_k of 3.2.1) besides the tile factors.
CORE_PARAMS: tuple[str, ...] = ("friction", "stiffness", "damping")


def sample_params(cfg: SimConfig, rng: np.random.Generator, source: str = "sim",
                  level: int | None = None) -> dict[str, float]:
    """Draw P_k: friction, stiffness, damping uniform in their intervals (3.2.1; for
    ``source="plant"`` the shifted ones of plant severity ``level``, default ``plant.level``)
    and one local adhesion factor per pad tile."""
    spec = source_spec(cfg, source, level)
    out = {name: float(rng.uniform(*getattr(spec, name))) for name in CORE_PARAMS}
    s = cfg.randomization.tile_spread
    for i, a in enumerate(rng.uniform(1.0 - s, 1.0 + s, cfg.scene.n_tiles)):
        out[f"tile_{i}"] = float(a)
    return out


def _check_params(cfg: SimConfig, params: dict[str, float]) -> dict[str, float]:
    out = {}
    for name in CORE_PARAMS:
        if name not in params:
            raise PeelError(f"params is missing '{name}'")
    for name, val in params.items():
        try:
            v = float(val)
        except (TypeError, ValueError):
            raise PeelError(f"params['{name}'] must be a number, got {val!r}") from None
        if not math.isfinite(v):
            raise PeelError(f"params['{name}'] must be finite, got {val!r}")
        if v < 0.0:
            raise PeelError(f"params['{name}'] must be >= 0, got {v!r}")
        out[name] = v
    for i in range(cfg.scene.n_tiles):
        out.setdefault(f"tile_{i}", 1.0)
    return out


class _Dyn:
    """Python-side dynamic state saved/restored with the engine state."""

    __slots__ = ("blade_mu", "f_coupling", "fx_true", "fz_true", "t", "u", "v_blade", "v_peel", "v_robot",
                 "x_robot")

    def __init__(self) -> None:
        self.t = 0.0
        self.x_robot = 0.0  # m
        self.v_robot = 0.0  # m/s (actual carriage speed)
        self.v_peel = 0.0  # m/s (relaxed blade speed, peel front)
        self.v_blade = 0.0  # m/s
        self.u = 0.0  # mm/s, last command
        self.blade_mu = 1.0
        self.f_coupling = 0.0
        self.fx_true = 0.0
        self.fz_true = 0.0

    def copy(self) -> _Dyn:
        d = _Dyn()
        for s in self.__slots__:
            setattr(d, s, getattr(self, s))
        return d


class PeelEnv:
    """The simulator (``source="sim"``) or the reality-gap plant (``source="plant"``).

    ``params`` given here fix the task's physical parameters for every :meth:`reset` that does
    not pass its own; with ``params=None`` each reset draws new ones from the env's generator.
    """

    def __init__(self, cfg: SimConfig, *, source: str = "sim", seed: int = 0,
                 params: dict[str, float] | None = None, effects: Sequence[Effect] = (),
                 level: int | None = None) -> None:
        if source not in SOURCES:
            raise PeelError(f"source must be one of {SOURCES}, got {source!r}")
        for e in effects:
            if not callable(e):
                raise PeelError(f"effects must be callables, got {type(e).__name__}")
        self.cfg = cfg
        self.source = source
        #: the plant severity level this env runs (level 0 for the simulator), docs/simulator.md
        self.plant: PlantSpec = source_spec(cfg, source, level)
        self.level = self.plant.level
        self.effects: list[Effect] = self.plant.effects() + list(effects)
        self._lag = self.plant.actuator_lag_s
        self._fixed_params = _check_params(cfg, params) if params is not None else None
        n = cfg.noise
        self.sensor = ForceSensor(n.force_resolution_n, n.force_sigma_n, n.force_bias_sigma_n,
                                  self.plant.drift_n_per_sqrt_s)
        self.scene = Scene(cfg)
        self._dt = cfg.task.dt_s
        self._nsub = cfg.scene.substeps
        self._cap = math.ceil(cfg.task.t_max_s / self._dt) + 2
        self._seed = seed
        self._cache_constants()
        self.reset(seed=seed)

    # ------------------------------------------------------------------ episode interface
    def reset(self, seed: int | None = None, params: dict[str, float] | None = None) -> Trajectory:
        """Start a new task at C (q = 0, at rest); returns the history with the t = 0 sample."""
        if seed is not None:
            self._seed = int(seed)
            self.rng = np.random.default_rng(self._seed)
        if params is not None:
            p = _check_params(self.cfg, params)
        elif self._fixed_params is not None:
            p = dict(self._fixed_params)
        else:
            p = sample_params(self.cfg, self.rng, self.source, self.level)
        self.params: dict[str, float] = p
        self._tile_list = [float(p[f"tile_{i}"]) for i in range(self._n_tiles)]
        self._damping = p["damping"]
        self._k_pad = PAD_CONTACT_POINTS * p["stiffness"]
        self.scene.apply_params(p["friction"], p["stiffness"], p["damping"])
        self.scene.reset_bodies()
        self.scene.set_blade_friction(self._mu_static)
        self.sensor.reset(self.rng)
        self.d = _Dyn()
        self.d.blade_mu = self._mu_static
        # settle the contacts at rest (no motion): one sample of engine steps
        for _ in range(self._nsub):
            self._engine_step(EffectAction(), 0.0)
        self.scene.reset_bodies()
        self.d.t = 0.0
        self._buf = np.full((self._cap, 7), np.nan)
        self._n = 0
        self.outcome = "running"
        fx, fz, psi = self._measure_true(0.0)
        self.d.fx_true, self.d.fz_true = fx, fz
        mfx, mfz = self.sensor.read(fx, fz, 0.0, self.rng)
        self._append(0.0, 0.0, 0.0, mfx, mfz, psi)
        self._blade_q = [self._x_blade / MM]
        self._hist: Trajectory | None = None
        return self.history

    @property
    def done(self) -> bool:
        """True once the task has ended (done, timeout or safety_stop)."""
        return self.outcome != "running"

    @property
    def history(self) -> Trajectory:
        """The task so far (paper units); ``outcome`` is ``running`` until the task ends."""
        if self._hist is None:
            rows = self._buf[: self._n]
            u = rows[:, 3].copy()
            u[np.isnan(u)] = 0.0
            self._hist = Trajectory(
                t=rows[:, 0], q=rows[:, 1], v=rows[:, 2], u=u, fx=rows[:, 4], fz=rows[:, 5],
                psi=rows[:, 6], outcome=self.outcome, params=dict(self.params),
                meta={"source": self.source, "seed": self._seed, "dt_s": self._dt,
                      "plant_level": self.level},
            )
        return self._hist

    @property
    def last_forces(self) -> tuple[float, float]:
        """(F_RX, F_RZ) of the latest sample, N, as measured."""
        row = self._buf[self._n - 1]
        return float(row[4]), float(row[5])

    def step(self, u_mmps: float) -> None:
        """Advance one sample (0.1 s) under the command ``u_mmps`` (mm/s)."""
        if self.done:
            raise PeelError(f"step() after the task ended ({self.outcome}); call reset()")
        u = float(u_mmps)
        if not math.isfinite(u):
            raise PeelError(f"command u_mmps must be finite, got {u_mmps!r}")
        scatter = self.rng.normal(0.0, self._v_sigma)
        q_prev = self._buf[self._n - 1, 1]
        self._buf[self._n - 1, 3] = u
        fx, fz, psi = self._advance(u, scatter)
        t = self._n * self._dt
        mfx, mfz = self.sensor.read(fx, fz, self._dt, self.rng)
        # q is the robot's own (encoder) position of the carriage, as the real arm reports it; the
        # blade lags it by the compliance deflection F_RX / k, so stick-slip shows in the forces
        # while v = (q_k - q_{k-1}) / dt scatters around the command u (Eq. 2).
        q = self.d.x_robot / MM
        self._append(t, q, (q - q_prev) / self._dt, mfx, mfz, psi)
        self._blade_q.append(self._x_blade / MM)
        if abs(mfx) >= self._f_prewarn or abs(mfz) >= self._f_prewarn:
            self.outcome = "safety_stop"
        elif q >= self._q_ter:
            self.outcome = "done"
        elif t >= self._t_end:
            self.outcome = "timeout"
        self._hist = None

    @property
    def blade_q_mm(self) -> np.ndarray:
        """Diagnostic (not a sensor): the blade's own position per sample, mm. It lags the
        carriage position ``q`` by the compliance deflection and shows the stick-slip."""
        return np.asarray(self._blade_q, dtype=np.float64)

    def close(self) -> None:
        """Release the PyBullet client."""
        self.scene.close()

    def __enter__(self) -> PeelEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ oracle
    def rollout(self, v: np.ndarray) -> np.ndarray:
        """True noise-free dynamics from the current state: for each of the N rows of ``v``
        (mm/s, one command per sample, shape [N, S]) the (q_mm, fx_N, fz_N) after each sample,
        shape [N, S, 3]. Effects apply; actuator scatter and sensor noise do not. The env is
        left exactly as it was."""
        v = np.asarray(v, dtype=np.float64)
        if v.ndim != 2:
            raise PeelError(f"rollout v must have shape [N, S], got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise PeelError("rollout v must be finite")
        out: list[tuple[float, float, float]] = []
        sid = self.scene.save()
        saved = self.d.copy()
        try:
            for row in v.tolist():
                self.scene.restore(sid)
                self.d = saved.copy()
                self.scene.set_blade_friction(self.d.blade_mu)
                self.scene.set_local(self._tile_factor(self.scene.blade_state()[0]))
                for u in row:
                    fx, fz, _ = self._advance(u, 0.0)
                    out.append((self.d.x_robot / MM, fx, fz))
        finally:
            self.scene.restore(sid)
            self.scene.remove_state(sid)
            self.d = saved
            self.scene.set_blade_friction(self.d.blade_mu)
            self.scene.set_local(self._tile_factor(self.scene.blade_state()[0]))
        return np.array(out, dtype=np.float64).reshape(v.shape[0], v.shape[1], 3)

    # ------------------------------------------------------------------ internals
    def _append(self, t: float, q: float, v: float, fx: float, fz: float, psi: float) -> None:
        self._buf[self._n] = (t, q, v, np.nan, fx, fz, psi)
        self._n += 1

    def _tile_factor(self, x_m: float) -> float:
        i = int((x_m - self._tile_x0) / self._tile_len)
        return self._tile_list[min(max(i, 0), self._n_tiles - 1)]

    def _cache_constants(self) -> None:
        """Plain-float copies of the per-step constants. ``SimConfig`` group lookups build a
        dict per access (tens of microseconds, more than a physics step's Python), so nothing
        on the per-sample or per-step path reads ``self.cfg``."""
        cfg = self.cfg
        sc, ld, tk, cc = cfg.scene, cfg.load, cfg.task, cfg.compensation
        self._tile_x0 = self.scene.tile_x0
        self._tile_len = sc.tile_length_mm * MM
        self._n_tiles = sc.n_tiles
        self._mu_static = (sc.static_friction_ratio if self.plant.static_friction_ratio is None
                           else self.plant.static_friction_ratio)
        self._v_stick = sc.stick_speed_mmps * MM
        self._k_c = sc.coupling_stiffness_n_per_mm / MM
        self._c_c = sc.coupling_damping_ns_per_mm / MM
        self._dtp = self.scene.dt_phys
        self._a_peel = 1.0 - math.exp(-self._dtp / ld.rate_tau_s)
        self._a_lag = 1.0 - math.exp(-self._dtp / self._lag) if self._lag > 0.0 else 1.0
        self._base_n = ld.base_n * self.plant.base_load_scale
        self._v_ref = ld.rate_ref_mmps * MM
        self._rate_n = ld.rate_exponent
        self._rate_gain = ld.rate_gain * self.plant.rate_gain_scale
        self._d_tool = sc.press_depth_mm * MM
        self._c_tool = sc.tool_compliance_z_mm_per_n * MM  # m/N
        self._w_sub = sc.substrate_mass_kg * 9.81
        self._v_sigma = cfg.noise.velocity_sigma_mmps
        self._f_prewarn = tk.f_prewarn_n
        self._q_ter = tk.q_ter_mm
        self._t_end = tk.t_max_s - 1e-9
        self._comp_on = bool(cc.enabled)
        self._e, self._b, self._h = cc.youngs_modulus_n_per_mm2, cc.width_mm, cc.thickness_mm
        self._alpha_deg = cc.alpha_deg
        self._phi_deg = bool(cc.phi_unit_deg)
        self._lp0 = cc.peeled_length_0_mm

    def _advance(self, u: float, scatter: float) -> tuple[float, float, float]:
        """One sample of dynamics under command u (mm/s); returns true (fx, fz, psi)."""
        d = self.d
        if self.effects:
            x_b, xd_b = self.scene.blade_state()
            st = EffectState(t_s=d.t, q_mm=x_b / MM, v_mmps=xd_b / MM, u_mmps=u,
                             fx_n=d.fx_true, fz_n=d.fz_true, params=self.params)
            act = combine([e(st) for e in self.effects])
        else:
            act = _NO_ACTION
        d.u = u
        target = ((u * act.v_scale + act.v_offset_mmps) + scatter) * MM
        self._substeps(target, act.resist_n, act.load_n)
        d.t += self._dt
        fx, fz, psi = self._measure_true(act.resist_n)
        d.fx_true, d.fz_true = fx, fz
        return fx, fz, psi

    def _substeps(self, target: float, resist_n: float, load_n: float) -> None:
        """The engine steps of one sample, the robot speed following ``target`` (m/s).

        This is the simulator's hot loop. Per engine step: the robot carriage moves (through the
        plant's lag), the pad takes the local adhesion of the tile under the blade, the blade's
        pad friction is static while it sticks and kinetic while it slides (stick-slip), the
        compliance pulls the blade towards the carriage and the substrate is pulled onto the
        blade by ``a(q) * (base + rate_gain * damping * v_ref * (v_peel / v_ref)^n) + load``.
        :meth:`_engine_step` is the same step written out plainly (``reset`` settles with it);
        this loop does the same arithmetic in the same order with the state in locals and the
        PyBullet functions bound once, so a step costs three PyBullet calls (joint state, two
        joint forces) besides ``stepSimulation``; ``changeDynamics`` is called only when the
        tile or the stick/slip state changes."""
        d = self.d
        scene = self.scene
        cid, blade, sub = scene.client, scene.blade, scene.substrate
        # positional arguments: getJointState(body, joint, client) and
        # setJointMotorControl2(body, joint, mode, targetPosition, targetVelocity, force)
        get_state, motor, step_sim = pb.getJointState, pb.setJointMotorControl2, pb.stepSimulation
        torque = pb.TORQUE_CONTROL
        tiles, x0, tile_len, last = self._tile_list, self._tile_x0, self._tile_len, self._n_tiles - 1
        a_lag, dtp, a_peel = self._a_lag, self._dtp, self._a_peel
        mu_static, v_stick, k_c, c_c = self._mu_static, self._v_stick, self._k_c, self._c_c
        v_ref, rate_n, base_n = self._v_ref, self._rate_n, self._base_n
        gain = self._rate_gain * self._damping * v_ref  # the left part of _engine_step's product
        d_tool, c_tool, w_sub, k_pad = self._d_tool, self._c_tool, self._w_sub, self._k_pad
        set_depth = scene.set_blade_depth
        v_robot, x_robot, v_peel, mu = d.v_robot, d.x_robot, d.v_peel, d.blade_mu
        cur_a, cur_mu = scene._local, scene._blade_mu
        f_c = xd_b = 0.0
        for _ in range(self._nsub):
            v_robot += (target - v_robot) * a_lag
            x_b, xd_b = get_state(blade, 0, cid)[:2]
            i = int((x_b - x0) / tile_len)
            a_loc = tiles[0 if i < 0 else (last if i > last else i)]
            if a_loc != cur_a:
                scene.set_local(a_loc)
                cur_a = a_loc
            x_robot += v_robot * dtp
            mu = mu_static if -v_stick < xd_b < v_stick else 1.0  # abs(xd_b) < v_stick
            if mu != cur_mu:
                scene.set_blade_friction(mu)
                cur_mu = mu
            f_c = k_c * (x_robot - x_b) + c_c * (v_robot - xd_b) - resist_n
            v_peel += ((0.0 if xd_b < 0.0 else xd_b) - v_peel) * a_peel  # max(xd_b, 0.0)
            load = a_loc * (base_n + gain * (v_peel / v_ref) ** rate_n) + load_n
            set_depth((d_tool + c_tool * (load + w_sub)) / (1.0 + c_tool * k_pad * a_loc))
            motor(blade, 0, torque, 0.0, 0.0, f_c, physicsClientId=cid)
            motor(sub, 0, torque, 0.0, 0.0, -load, physicsClientId=cid)
            step_sim(cid)
        d.v_robot, d.x_robot, d.v_peel, d.blade_mu = v_robot, x_robot, v_peel, mu
        d.v_blade = xd_b
        d.f_coupling = f_c + resist_n

    def _engine_step(self, act: EffectAction, v_robot: float) -> None:
        """One engine step, written plainly (see :meth:`_substeps`, which must match it)."""
        d = self.d
        scene = self.scene
        x_b, xd_b = scene.blade_state()
        a_loc = self._tile_factor(x_b)
        scene.set_local(a_loc)
        d.x_robot += v_robot * self._dtp
        # stick-slip: static friction while the blade sticks, kinetic while it slides
        mu = self._mu_static if abs(xd_b) < self._v_stick else 1.0
        d.blade_mu = mu
        scene.set_blade_friction(mu)
        f_c = self._k_c * (d.x_robot - x_b) + self._c_c * (v_robot - xd_b) - act.resist_n
        d.v_peel += (max(xd_b, 0.0) - d.v_peel) * self._a_peel
        v_ref = self._v_ref
        rate = self._rate_gain * self._damping * v_ref * (d.v_peel / v_ref) ** self._rate_n
        load = a_loc * (self._base_n + rate) + act.load_n
        # vertical compliance: tool spring (d_tool - psi) / c_tool + glass load = pad k_pad a psi
        self.scene.set_blade_depth(self._depth_eq(load, a_loc))
        d.v_blade = xd_b
        d.f_coupling = f_c + act.resist_n
        scene.substep(f_c, -load)

    def _depth_eq(self, load_n: float, a_loc: float) -> float:
        """Indentation psi (m) where the tool's vertical spring (compliance c, held at depth d by
        the robot), the glass load on the blade (vacuum / peel load + the glass's weight) and
        the pad's contact stiffness (``PAD_CONTACT_POINTS`` x k x a) balance:
        ``psi = (d + c (load + m_s g)) / (1 + c k_pad a)``; c = 0 gives psi = d (rigid)."""
        return (self._d_tool + self._c_tool * (load_n + self._w_sub)) / (
            1.0 + self._c_tool * self._k_pad * a_loc)

    def _measure_true(self, resist_n: float) -> tuple[float, float, float]:
        """True (F_RX, F_RZ) in N: engine contact forces + Eq. 21-22 (+ effect resistance),
        and the blade's indentation psi (mm). Leaves the blade position (m) in ``_x_blade``."""
        scene = self.scene
        fz_load, pen = scene.load_and_penetration()
        x_b, xd_b = scene.blade_state()
        self._x_blade = x_b
        # F_RX: the force the compliance (tool + wrist sensor) transmits to the blade, which
        # the engine's contacts resist; F_RZ: the engine's normal force of the glass on it.
        fx, fz = self.d.f_coupling + resist_n, fz_load
        if self._comp_on:
            phi, lp = comp.desorption_geometry(scene.substrate_lift() / MM, x_b / MM, self._lp0)
            cx, cz = comp.compensate(e_n_per_mm2=self._e, b_mm=self._b, h_mm=self._h,
                                     alpha_deg=self._alpha_deg, phi_rad=phi, lp_mm=lp,
                                     v_mmps=max(xd_b / MM, 0.0), phi_unit_deg=self._phi_deg)
            fx += cx
            fz += cz
        return fx, fz, pen / MM
