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

The task ends at q >= q_ter (``done``), on |F_RX| or |F_RZ| >= 20 N (``safety_stop``) or at
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
from .config import SimConfig
from .effects import Effect, EffectAction, EffectState, combine
from .noise import ForceSensor
from .plant import SOURCES, actuator_lag_s, declared_effects, drift_rate
from .scene import MM, Scene

_NO_ACTION = EffectAction()

#: Physical parameters that define one task (P_k of 3.2.1) besides the tile factors.
CORE_PARAMS: tuple[str, ...] = ("friction", "stiffness", "damping")


def sample_params(cfg: SimConfig, rng: np.random.Generator, source: str = "sim") -> dict[str, float]:
    """Draw P_k: friction, stiffness, damping uniform in their intervals (3.2.1; the plant's
    shifted ones for ``source="plant"``) and one local adhesion factor per pad tile."""
    if source not in SOURCES:
        raise PeelError(f"source must be one of {SOURCES}, got {source!r}")
    grp = cfg.randomization if source == "sim" else cfg.plant
    out = {
        name: float(rng.uniform(getattr(grp, name + "_low"), getattr(grp, name + "_high")))
        for name in CORE_PARAMS
    }
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
                 params: dict[str, float] | None = None, effects: Sequence[Effect] = ()) -> None:
        if source not in SOURCES:
            raise PeelError(f"source must be one of {SOURCES}, got {source!r}")
        for e in effects:
            if not callable(e):
                raise PeelError(f"effects must be callables, got {type(e).__name__}")
        self.cfg = cfg
        self.source = source
        self.effects: list[Effect] = (declared_effects(cfg) if source == "plant" else []) + list(
            effects)
        self._lag = actuator_lag_s(cfg, source)
        self._fixed_params = _check_params(cfg, params) if params is not None else None
        n = cfg.noise
        self.sensor = ForceSensor(n.force_resolution_n, n.force_sigma_n, n.force_bias_sigma_n,
                                  drift_rate(cfg, source))
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
            p = sample_params(self.cfg, self.rng, self.source)
        self.params: dict[str, float] = p
        self._tiles = np.array([p[f"tile_{i}"] for i in range(self.cfg.scene.n_tiles)])
        self._damping = p["damping"]
        self.scene.apply_params(p["friction"], p["stiffness"], p["damping"])
        self.scene.reset_bodies()
        self.scene.set_blade_friction(self.cfg.scene.static_friction_ratio)
        self.sensor.reset(self.rng)
        self.d = _Dyn()
        self.d.blade_mu = self.cfg.scene.static_friction_ratio
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
                meta={"source": self.source, "seed": self._seed, "dt_s": self._dt},
            )
        return self._hist

    def step(self, u_mmps: float) -> None:
        """Advance one sample (0.1 s) under the command ``u_mmps`` (mm/s)."""
        if self.done:
            raise PeelError(f"step() after the task ended ({self.outcome}); call reset()")
        u = float(u_mmps)
        if not math.isfinite(u):
            raise PeelError(f"command u_mmps must be finite, got {u_mmps!r}")
        scatter = self.rng.normal(0.0, self.cfg.noise.velocity_sigma_mmps)
        q_prev = self._buf[self._n - 1, 1]
        self._buf[self._n - 1, 3] = u
        fx, fz, psi = self._advance(u, scatter)
        t = self._n * self._dt
        mfx, mfz = self.sensor.read(fx, fz, self._dt, self.rng)
        q = self.scene.blade_state()[0] / MM
        self._append(t, q, (q - q_prev) / self._dt, mfx, mfz, psi)
        tk = self.cfg.task
        if abs(mfx) >= tk.f_prewarn_n or abs(mfz) >= tk.f_prewarn_n:
            self.outcome = "safety_stop"
        elif q >= tk.q_ter_mm:
            self.outcome = "done"
        elif t >= tk.t_max_s - 1e-9:
            self.outcome = "timeout"
        self._hist = None

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
        out = np.empty((v.shape[0], v.shape[1], 3))
        sid = self.scene.save()
        saved = self.d.copy()
        try:
            for i in range(v.shape[0]):
                self.scene.restore(sid)
                self.d = saved.copy()
                self.scene.set_blade_friction(self.d.blade_mu)
                self.scene.set_local(self._tile_factor(self.scene.blade_state()[0]))
                for j in range(v.shape[1]):
                    fx, fz, _ = self._advance(float(v[i, j]), 0.0)
                    out[i, j, 0] = self.scene.blade_state()[0] / MM
                    out[i, j, 1] = fx
                    out[i, j, 2] = fz
        finally:
            self.scene.restore(sid)
            self.scene.remove_state(sid)
            self.d = saved
            self.scene.set_blade_friction(self.d.blade_mu)
            self.scene.set_local(self._tile_factor(self.scene.blade_state()[0]))
        return out

    # ------------------------------------------------------------------ internals
    def _append(self, t: float, q: float, v: float, fx: float, fz: float, psi: float) -> None:
        self._buf[self._n] = (t, q, v, np.nan, fx, fz, psi)
        self._n += 1

    def _tile_factor(self, x_m: float) -> float:
        i = int((x_m - self._tile_x0) / self._tile_len)
        return float(self._tiles[min(max(i, 0), self._n_tiles - 1)])

    def _cache_constants(self) -> None:
        """Plain-float copies of the per-step constants (config lookups are slow)."""
        sc, ld = self.cfg.scene, self.cfg.load
        self._tile_x0 = self.scene.tile_x0
        self._tile_len = sc.tile_length_mm * MM
        self._n_tiles = sc.n_tiles
        self._mu_static = sc.static_friction_ratio
        self._v_stick = sc.stick_speed_mmps * MM
        self._k_c = sc.coupling_stiffness_n_per_mm / MM
        self._c_c = sc.coupling_damping_ns_per_mm / MM
        self._dtp = self.scene.dt_phys
        self._a_peel = 1.0 - math.exp(-self._dtp / ld.rate_tau_s)
        self._a_lag = 1.0 - math.exp(-self._dtp / self._lag) if self._lag > 0.0 else 1.0
        self._base_n = ld.base_n
        self._v_ref = ld.rate_ref_mmps * MM
        self._rate_n = ld.rate_exponent
        self._rate_gain = ld.rate_gain

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
        a_lag = self._a_lag
        for _ in range(self._nsub):
            d.v_robot += (target - d.v_robot) * a_lag
            self._engine_step(act, d.v_robot)
        d.t += self._dt
        fx, fz, psi = self._measure_true(act.resist_n)
        d.fx_true, d.fz_true = fx, fz
        return fx, fz, psi

    def _engine_step(self, act: EffectAction, v_robot: float) -> None:
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
        d.v_blade = xd_b
        d.f_coupling = f_c + act.resist_n
        scene.substep(f_c, -load)

    def _measure_true(self, resist_n: float) -> tuple[float, float, float]:
        """True (F_RX, F_RZ) in N: engine contact forces + Eq. 21-22 (+ effect resistance),
        and the blade's indentation psi (mm)."""
        _fx_c, fz_load, _fz_pad, pen = self.scene.contact_forces()
        # F_RX: the force the compliance (tool + wrist sensor) transmits to the blade, which
        # the engine's contacts resist; F_RZ: the engine's normal force of the glass on it.
        fx, fz = self.d.f_coupling + resist_n, fz_load
        cc = self.cfg.compensation
        if cc.enabled:
            x_b, xd_b = self.scene.blade_state()
            phi, lp = comp.desorption_geometry(self.scene.substrate_lift() / MM, x_b / MM,
                                               cc.peeled_length_0_mm)
            cx, cz = comp.compensate(
                e_n_per_mm2=cc.youngs_modulus_n_per_mm2, b_mm=cc.width_mm, h_mm=cc.thickness_mm,
                alpha_deg=cc.alpha_deg, phi_rad=phi, lp_mm=lp, v_mmps=max(xd_b / MM, 0.0),
                phi_unit_deg=cc.phi_unit_deg,
            )
            fx += cx
            fz += cz
        return fx, fz, pen / MM
