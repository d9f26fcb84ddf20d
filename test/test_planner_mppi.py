"""OL-MPPI core (Algorithm 2, Eq. 31, Eq. 38): weights, convergence, Sigma, model swap."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory
from peel_planner_node.config import PlannerConfig
from peel_planner_node.cost import Cost, Critic, Rollouts
from peel_planner_node.mppi import (
    Planner,
    ar1_matrix,
    ar1_precision,
    control_cost,
    eq38_weights,
    term_influence,
)

torch.set_num_threads(1)


def start_history(q: float = 0.0, t: float = 0.0) -> Trajectory:
    return Trajectory(t=[t], q=[q], v=[0.0], u=[0.0], fx=[1.0], fz=[1.0], psi=[np.nan])


def append(hist: Trajectory, v: float, n: int = 5, u: float = 0.0) -> Trajectory:
    """The history after n samples at measured velocity v (forces stay small)."""
    arr = hist.as_array()
    rows = []
    t, q = arr[-1, 0], arr[-1, 1]
    for _ in range(n):
        t, q = t + 0.1, q + 0.1 * v
        rows.append([t, q, v, u, 1.0, 1.0, np.nan])
    return Trajectory.from_array(np.vstack([arr, np.array(rows)]))


class LinearDynamics:
    """q_s = q_now + dt * cumsum(v); fx = a * v; fz = b."""

    def __init__(self, a: float = 1.5, b: float = 3.0, dt: float = 0.1) -> None:
        self.a, self.b, self.dt = a, b, dt
        self.calls = 0

    def rollout(self, history: Trajectory, v: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        q = float(history.q[-1]) + self.dt * torch.cumsum(v, dim=1)
        return torch.stack([q, self.a * v, torch.full_like(v, self.b)], dim=-1)


class QuadraticCritic(Critic):
    """J = w/2 * sum_s (q_s - target_s)^2 over the model steps of a rollout (positions
    uncapped: the target is far from q_ter)."""

    name = "quadratic"

    def __init__(self, target: torch.Tensor, w: float) -> None:
        self.target, self.w = target, w

    def score(self, r: Rollouts) -> torch.Tensor:
        return 0.5 * self.w * ((r.q - self.target) ** 2).sum(dim=1)


def config(**flat) -> PlannerConfig:
    return PlannerConfig().replace(**flat)


# ---------------------------------------------------------------- Eq. 38
def direct_eq38(cost, eps, u, sigma, lam):
    """Unvectorised Eq. 38: omega_k = exp(-(J_k + lam/2 sum_t (u Sinv u + 2 eps Sinv u))/lam)/eta."""
    n, h = len(eps), len(u)
    s = []
    for k in range(n):
        ctrl = 0.0
        for t in range(h):
            ctrl += u[t] * (1.0 / sigma) * u[t] + 2.0 * eps[k][t] * (1.0 / sigma) * u[t]
        s.append(cost[k] + lam / 2.0 * ctrl)
    unnorm = [math.exp(-sk / lam) for sk in s]
    eta = sum(unnorm)
    return [w / eta for w in unnorm]


def test_eq38_weights_equal_direct_evaluation() -> None:
    rng = np.random.default_rng(3)
    n, h, sigma, lam = 6, 4, 0.7, 0.5
    cost = rng.uniform(0.0, 2.0, n)
    eps = rng.normal(0.0, math.sqrt(sigma), (n, h))
    u = rng.uniform(0.5, 2.0, h)
    want = direct_eq38(cost.tolist(), eps.tolist(), u.tolist(), sigma, lam)
    got = eq38_weights(torch.tensor(cost), torch.tensor(eps), torch.tensor(u), sigma, lam)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-10, atol=1e-14)
    assert got.sum().item() == pytest.approx(1.0, abs=1e-12)


def test_planner_update_uses_eq38_and_eq31() -> None:
    """One update of the real planner: its omega is Eq. 38 (the paper's per-step form) of its
    samples, U = sum omega v."""
    cfg = config(**{"mppi.n_samples": 7, "mppi.horizon": 3, "mppi.dtype": "float64",
                    "mppi.lambda": 0.3, "mppi.sigma0": 0.8, "mppi.u_init": 2.0,
                    "mppi.control_cost_scale": 1.0, "mppi.control_term": "per_step"})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    u_before = planner.U.clone()
    u_after = planner.update(append(start_history(), 1.0))
    last = planner.last
    v = last["v"].numpy()
    eps = last["eps"].numpy()
    np.testing.assert_allclose(eps, v - u_before.numpy()[None, :], atol=1e-12)
    want = direct_eq38(last["cost"].tolist(), eps.tolist(), u_before.tolist(), 0.8, 0.3)
    np.testing.assert_allclose(last["omega"].numpy(), want, rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(u_after, (np.array(want)[:, None] * v).sum(axis=0), rtol=1e-9)
    assert np.all(v >= cfg.mppi.u_min) and np.all(v <= cfg.mppi.u_max)


@pytest.mark.parametrize("which", ["estimate", "sigma0"])
def test_control_term_uses_the_configured_sigma(which: str) -> None:
    """After Sigma was re-estimated (0.09 -> floor 0.25 here), Eq. 38's control term uses the
    estimate (``control_cost_sigma: estimate``, the paper) or sigma0 (``sigma0``), while the
    noise is drawn with the estimate either way."""
    cfg = config(**{"mppi.n_samples": 9, "mppi.horizon": 3, "mppi.dtype": "float64",
                    "mppi.lambda": 0.3, "mppi.sigma0": 0.8, "mppi.u_init": 2.0,
                    "mppi.sigma_min_count": 1, "mppi.control_cost_scale": 1.0,
                    "mppi.sigma_min": 0.25, "mppi.control_cost_sigma": which,
                    "mppi.control_term": "per_step"})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    planner.observe(2.3, 2.0)
    assert planner.sigma == pytest.approx(0.25)
    u_before = planner.U.clone()
    planner.update(append(start_history(), 1.0))
    last = planner.last
    eps = last["eps"].numpy()
    assert np.abs(eps).max() < 4.0 * math.sqrt(0.25)  # drawn with the estimate
    sigma_ctrl = 0.25 if which == "estimate" else 0.8
    want = direct_eq38(last["cost"].tolist(), eps.tolist(), u_before.tolist(), sigma_ctrl, 0.3)
    np.testing.assert_allclose(last["omega"].numpy(), want, rtol=1e-9, atol=1e-14)
    other = direct_eq38(last["cost"].tolist(), eps.tolist(), u_before.tolist(),
                        0.8 if which == "estimate" else 0.25, 0.3)
    assert not np.allclose(last["omega"].numpy(), other, rtol=1e-3)


# ---------------------------------------------------------------- convergence (LQ case)
@pytest.mark.parametrize(("scale", "rho", "term"), [(1.0, 0.0, "per_step"),
                                                    (0.0, 0.0, "per_step"),
                                                    (1.0, 0.8, "per_step"),
                                                    (0.0, 0.8, "per_step"),
                                                    (1.0, 0.8, "joint")])
def test_linear_quadratic_plan_converges_to_known_optimum(scale: float, rho: float,
                                                          term: str) -> None:
    """Linear model q = q0 + A V and J = w/2 |A V - b|^2: MPPI's fixed point U has E_q[eps] = 0
    for q(eps) ~ exp(-J(U + eps)/lambda - c U' P eps / Sigma) N(0, Sigma R), with R the noise's
    correlation over the horizon and P the precision in Eq. 38's control term, i.e.
    (w A'A + c lambda/Sigma R^-1 P R ... ) -- for P = R^-1 (joint term, or white noise with the
    per-step term) U* = (w A'A + c lambda/Sigma R^-1)^-1 w A'b, the mean of the prior N(0,
    Sigma R) tilted by exp(-J/lambda); for AR(1) noise with the per-step term (P = I) it is
    (w A'A + c lambda/Sigma I)^-1 w A'b whatever R is. c = 0: the unregularised minimiser."""
    h, k, dt, sigma, lam, w = 3, 5, 0.1, 1.0, 0.1, 0.2
    cfg = config(**{"mppi.n_samples": 4000, "mppi.horizon": h, "mppi.lambda": lam,
                    "mppi.sigma0": sigma, "mppi.u_min": -50.0, "mppi.u_max": 50.0,
                    "mppi.u_init": 0.0, "mppi.dtype": "float64", "mppi.seed": 11,
                    "mppi.control_cost_scale": scale, "mppi.noise_correlation": rho,
                    "mppi.control_term": term})
    s = h * k
    lower = np.tril(np.ones((s, s)))
    expand = np.kron(np.eye(h), np.ones((k, 1)))
    a = dt * lower @ expand                       # q = q0 + A V
    r = np.array([2.0, 1.0, 3.0])                 # velocities that would hit the target
    b = a @ r                                     # target minus q0 (q0 = 0)
    prior = (ar1_precision(h, rho, torch.float64).numpy() if term == "joint"
             else np.eye(h))
    v_star = np.linalg.solve(w * a.T @ a + scale * lam / sigma * prior, w * a.T @ b)
    cost = Cost(cfg.cost, critics=[QuadraticCritic(torch.tensor(b), w)])
    planner = Planner(LinearDynamics(dt=dt), cost, cfg)
    hist = start_history()
    # correlated noise explores the alternating direction of V little: slower convergence
    iters = 60 if rho == 0.0 else 300
    trail = [planner.update(hist) for _ in range(iters)]
    got = np.mean(trail[iters // 2:], axis=0)
    np.testing.assert_allclose(got, v_star, atol=0.05)
    if scale == 1.0:  # the control term's shrinkage is visible, so this test can tell them apart
        assert np.max(np.abs(v_star - r)) > 0.3
        other = np.linalg.solve(w * a.T @ a + lam / sigma * (
            np.eye(h) if term == "joint" else ar1_precision(h, 0.8, torch.float64).numpy()),
            w * a.T @ b)
        if rho > 0.0:  # the two control terms have different fixed points
            assert np.max(np.abs(v_star - other)) > 0.2
    else:
        np.testing.assert_allclose(v_star, r, atol=1e-9)


# ---------------------------------------------------------------- Eq. 38 with AR(1) noise
@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8, 0.95])
def test_ar1_precision_is_the_inverse_noise_correlation(rho: float) -> None:
    """R_ts = rho^|t-s| is the covariance of the sampled noise (A'A); its inverse is the
    tridiagonal matrix of ar1_precision."""
    for h in (1, 2, 5, 10):
        idx = np.arange(h)
        corr = rho ** np.abs(idx[:, None] - idx[None, :])
        prec = ar1_precision(h, rho, torch.float64).numpy()
        np.testing.assert_allclose(prec @ corr, np.eye(h), atol=1e-10)
        assert np.all(np.triu(prec, 2) == 0.0)
        if rho > 0.0:
            a = ar1_matrix(h, rho, torch.float64).numpy()
            np.testing.assert_allclose(a.T @ a, corr, atol=1e-12)


def test_joint_control_term_is_the_log_likelihood_ratio_of_the_horizon() -> None:
    """lambda log(p(V) / q_U(V)) of the whole horizon for p = N(0, Sigma R) and q_U = N(U,
    Sigma R) at V = U + eps, written with an explicit inverse, equals -control_cost with the
    AR(1) precision (c = 1); the per-step term is the same with R = I."""
    rng = np.random.default_rng(5)
    h, n, sigma, lam, rho = 5, 6, 0.7, 0.3, 0.8
    u, eps = rng.uniform(0.5, 3.0, h), rng.normal(0.0, 1.0, (n, h))
    idx = np.arange(h)
    for corr, prec in ((rho ** np.abs(idx[:, None] - idx[None, :]),
                        ar1_precision(h, rho, torch.float64)), (np.eye(h), None)):
        inv = np.linalg.inv(sigma * corr)
        v = u + eps
        log_ratio = np.array([-0.5 * vk @ inv @ vk + 0.5 * ek @ inv @ ek
                              for vk, ek in zip(v, eps, strict=True)])
        got = control_cost(torch.tensor(eps), torch.tensor(u), sigma, lam, 1.0, prec)
        np.testing.assert_allclose(got.numpy(), -lam * log_ratio, rtol=1e-10)


def test_planner_uses_the_configured_control_term() -> None:
    """``control_term: joint`` weights with the AR(1) precision of the horizon; per_step with
    the identity (Eq. 36-37); both checked against an explicit evaluation, and told apart."""
    omegas = {}
    for term in ("joint", "per_step"):
        cfg = config(**{"mppi.n_samples": 9, "mppi.horizon": 4, "mppi.dtype": "float64",
                        "mppi.lambda": 0.3, "mppi.sigma0": 0.8, "mppi.u_init": 2.0,
                        "mppi.control_cost_scale": 1.0, "mppi.noise_correlation": 0.8,
                        "mppi.control_term": term})
        planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
        u = planner.U.clone()
        planner.update(append(start_history(), 1.0))
        last = planner.last
        prec = ar1_precision(4, 0.8, torch.float64) if term == "joint" else torch.eye(
            4, dtype=torch.float64)
        s = last["cost"] + 0.5 * 0.3 / 0.8 * (u @ prec @ u + 2.0 * last["eps"] @ prec @ u)
        want = torch.exp(-(s - s.min()) / 0.3)
        torch.testing.assert_close(last["omega"], want / want.sum(), rtol=1e-9, atol=1e-14)
        omegas[term] = last["omega"]
    assert not torch.allclose(omegas["joint"], omegas["per_step"], rtol=1e-3)


# ---------------------------------------------------------------- Sigma (lines 15-17)
def run_with_errors(planner: Planner, errors: list[float], hist: Trajectory) -> list[float]:
    """Plan, then let the blade move at u* + e for one control period; returns Sigma after each."""
    sigmas = []
    for e in errors:
        u = planner.plan(hist)
        hist = append(hist, u + e, u=u)
        planner.plan(hist)  # measures v* for the previous command
        planner._issued = None  # measure exactly one error per injected value
        sigmas.append(planner.sigma)
    return sigmas


def test_sigma_follows_injected_velocity_errors() -> None:
    cfg = config(**{"mppi.sigma0": 1.0, "mppi.sigma_window": 6, "mppi.sigma_min_count": 3,
                    "mppi.sigma_min": 0.01, "mppi.sigma_max": 9.0, "mppi.u_max": 3.0})
    planner = Planner(LinearDynamics(a=0.1), Cost(cfg.cost), cfg)
    hist = start_history()
    s1 = run_with_errors(planner, [0.8, -0.8] * 4, hist)
    assert s1[0] == pytest.approx(1.0)          # fewer than sigma_min_count errors: sigma0
    assert s1[-1] == pytest.approx(0.64, rel=1e-6)
    s2 = run_with_errors(planner, [1.5, -1.5] * 4, hist)
    assert s2[0] < 2.25 and s2[-1] == pytest.approx(2.25, rel=1e-6)
    s3 = run_with_errors(planner, [0.0] * 6, hist)
    assert s3[-1] == pytest.approx(0.01)        # floor
    s4 = run_with_errors(planner, [5.0] * 6, hist)
    assert s4[-1] == pytest.approx(9.0)         # ceiling


def test_sigma_estimates_gaussian_error_variance() -> None:
    cfg = config(**{"mppi.sigma_window": 400, "mppi.sigma_min": 0.01, "mppi.sigma_max": 50.0})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    rng = np.random.default_rng(0)
    for e in rng.normal(0.0, 1.7, 400):
        planner.observe(2.0 + e, 2.0)
    assert planner.sigma == pytest.approx(1.7 ** 2, rel=0.15)


def test_plan_measures_average_velocity_of_the_period() -> None:
    cfg = config(**{"mppi.sigma_min_count": 1, "mppi.sigma_min": 1e-6})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    hist = start_history()
    u = planner.plan(hist)
    planner.plan(append(hist, u + 0.5, u=u))
    assert list(planner.errors) == [pytest.approx(0.5)]
    assert planner.sigma == pytest.approx(0.25)


# ---------------------------------------------------------------- state, swap, limits
def test_set_dynamics_keeps_planner_state() -> None:
    cfg = config(**{"mppi.sigma_min_count": 1})
    d1, d2 = LinearDynamics(a=1.0), LinearDynamics(a=2.0)
    planner = Planner(d1, Cost(cfg.cost), cfg)
    hist = start_history()
    for _ in range(3):
        u = planner.plan(hist)
        hist = append(hist, u + 0.3, u=u)
    state = (planner.U.clone(), planner.sigma, list(planner.errors), planner._issued,
             planner._gen.get_state().clone())
    planner.set_dynamics(d2)
    assert torch.equal(planner.U, state[0]) and planner.sigma == state[1]
    assert list(planner.errors) == state[2] and planner._issued == state[3]
    assert torch.equal(planner._gen.get_state(), state[4])
    calls = d1.calls
    planner.plan(hist)
    assert d1.calls == calls and d2.calls == 1
    assert len(planner.errors) == len(state[2]) + 1


def test_same_seed_same_plan_and_reset_restarts() -> None:
    cfg = PlannerConfig()
    hist = append(start_history(), 1.0)
    p1 = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    p2 = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    a = [p1.plan(hist) for _ in range(3)]
    b = [p2.plan(hist) for _ in range(3)]
    assert a == b
    p1.reset()
    assert p1.plan(hist) == a[0]


def test_commands_stay_within_speed_limits() -> None:
    cfg = config(**{"mppi.u_min": 0.5, "mppi.u_max": 2.0, "mppi.sigma0": 4.0, "mppi.u_init": 1.0,
                    "mppi.sigma_min_count": 100, "cost.progress.weight": 15.0})
    planner = Planner(LinearDynamics(a=0.0, b=0.0), Cost(cfg.cost), cfg)
    hist = start_history()
    for _ in range(6):
        u = planner.plan(hist)
        assert 0.5 <= u <= 2.0
        assert float(planner.last["v"].min()) >= 0.5 and float(planner.last["v"].max()) <= 2.0
        hist = append(hist, u, u=u)
    assert u > 1.5  # no force penalty: progress drives it towards u_max


def test_shift_moves_u_by_one_horizon_step() -> None:
    cfg = config(**{"mppi.shift_fill": "init", "mppi.u_init": 0.7})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    hist = start_history()
    planner.update(hist)
    before = planner.U.clone()
    planner._shift()
    np.testing.assert_allclose(planner.U[:-1].numpy(), before[1:].numpy())
    assert float(planner.U[-1]) == pytest.approx(0.7)


def test_bad_dynamics_output_is_refused() -> None:
    class Wrong:
        def rollout(self, history, v):
            return torch.zeros(v.shape[0], 3, 3)

    planner = Planner(Wrong(), Cost(), PlannerConfig())
    with pytest.raises(PeelError, match="shape"):
        planner.plan(start_history())
    with pytest.raises(PeelError, match="rollout"):
        planner.set_dynamics(object())


def test_planner_does_not_configure_its_dynamics() -> None:
    """The Planner only calls rollout(): the dynamics' own settings (threads, chunks) are its
    config section's, and a dynamics with other methods is left alone."""
    class Configurable(LinearDynamics):
        def set_workers(self, *args) -> None:
            raise AssertionError("the planner must not configure the dynamics")

    cfg = config()
    planner = Planner(Configurable(), Cost(cfg.cost), cfg)
    planner.set_dynamics(Configurable())
    assert planner.plan(start_history()) > 0.0



@pytest.mark.parametrize("flat", [{}, {"mppi.noise_correlation": 0.6},
                                  {"mppi.dtype": "float64", "mppi.control_cost_scale": 0.3}])
def test_update_weights_equal_the_former_inline_eq38(flat, monkeypatch) -> None:
    """Planner.update weights through eq38_weights; on random costs (a dynamics with random
    forces) omega equals, bit for bit, the softmax the update used to compute in place."""
    import peel_planner_node.mppi as mppi

    calls = []
    real = mppi.eq38_weights

    def spy(*args, **kw):
        calls.append(args)
        return real(*args, **kw)

    monkeypatch.setattr(mppi, "eq38_weights", spy)
    cfg = config(**flat)
    rng = np.random.default_rng(5)
    planner = Planner(LinearDynamics(a=float(rng.uniform(0.5, 3.0)),
                                     b=float(rng.uniform(0.5, 5.0))), Cost(cfg.cost), cfg)
    hist = start_history()
    for v in rng.uniform(0.2, 3.0, 3):
        planner.update(hist := append(hist, float(v)))
        last = planner.last
        s = last["cost"] + last["control"]
        old = torch.softmax(-(s - s.min()) / planner.lam, dim=0)
        assert torch.equal(last["omega"], old)
    assert len(calls) == 3

def test_terms_of_the_plan_are_kept_for_diagnostics() -> None:
    """Every critic's N costs (summing to J) and Eq. 38's control term are in planner.last;
    term_influence is each term's mean minus its omega-weighted mean."""
    cfg = config(**{"mppi.dtype": "float64"})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    planner.update(append(start_history(), 1.0))
    last = planner.last
    assert set(last["terms"]) == {"progress", "force_x", "force_z", "terminal", "barrier",
                                  "cost_to_go"}
    torch.testing.assert_close(sum(last["terms"].values()), last["cost"])
    influence = term_influence({**last["terms"], "control": last["control"]}, last["omega"])
    s = last["cost"] + last["control"]
    assert sum(influence.values()) == pytest.approx(float(s.mean() - last["omega"] @ s))
    assert sum(influence.values()) > 0.0  # the weighting lowers S


def test_correlated_noise_keeps_sigma_per_step_and_has_rho_lag_one() -> None:
    """noise_correlation rho: eps_t = rho eps_(t-1) + sqrt(1 - rho^2) z_t, so every eps_t is
    N(0, Sigma) as Eq. 2 wants, with correlation rho^|t - s| between horizon steps."""
    cfg = config(**{"mppi.n_samples": 20000, "mppi.horizon": 5, "mppi.noise_correlation": 0.8,
                    "mppi.u_min": -50.0, "mppi.u_max": 50.0, "mppi.sigma0": 0.7,
                    "mppi.dtype": "float64", "safety.null_sample": False})
    planner = Planner(LinearDynamics(), Cost(cfg.cost), cfg)
    planner.update(start_history())
    eps = planner.last["eps"].numpy()  # the N sampled rows only: no slowest sequence
    np.testing.assert_allclose(eps.var(axis=0), 0.7, rtol=0.05)
    corr = np.corrcoef(eps.T)
    for lag in (1, 2, 4):
        np.testing.assert_allclose(np.diag(corr, lag), 0.8 ** lag, atol=0.03)
    white = Planner(LinearDynamics(), Cost(cfg.cost), cfg.replace(**{"mppi.noise_correlation": 0.0}))
    white.update(start_history())
    assert np.abs(np.diag(np.corrcoef(white.last["eps"].numpy().T), 1)).max() < 0.03
