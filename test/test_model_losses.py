"""L_MSE + kappa L_PENE (Eq. 23-25) and RMSE / Corr (Eq. 39-40)."""

import numpy as np
import pytest
import torch

from model_learner_node.losses import batch_loss, mse_loss, pene_loss, total_loss
from model_learner_node.metrics import corr, rmse
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, Normalization


def test_pene_zero_within_limit_and_positive_beyond():
    lim = 0.2
    assert float(pene_loss(torch.tensor([-1.0, 0.0, 0.1, 0.2]), lim)) == 0.0
    beyond = pene_loss(torch.tensor([0.0, 0.5]), lim)
    assert float(beyond) == pytest.approx((0.3**2) / 2)
    assert float(pene_loss(torch.tensor([0.2 + 1e-3]), lim)) > 0.0
    # grows with the violation
    assert float(pene_loss(torch.tensor([0.6]), lim)) > float(pene_loss(torch.tensor([0.4]), lim))


def test_mse_scaled_per_channel():
    f_hat = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    f = torch.tensor([[0.0, 2.0], [3.0, 0.0]])
    assert float(mse_loss(f_hat, f)) == pytest.approx((1 + 16) / 4)
    assert float(mse_loss(f_hat, f, torch.tensor([1.0, 2.0]))) == pytest.approx((1 + 4) / 4)


def test_total_loss_uses_predicted_psi_from_fz():
    torch.manual_seed(0)
    norm = Normalization(pad_compliance_mm_per_n=0.1)
    p = ForcePredictor(ModelConfig(arch="mlp"), norm)
    hist = torch.zeros(8, 10, 4)
    hist[:, :, 3] = 50.0  # F_RZ = 50 N -> psi ~ 5 mm >> psi_lim
    v = torch.zeros(8)
    target = p(hist, v).detach()
    loss, parts = total_loss(p, hist, v, target, kappa=1.0, psi_lim=0.2)
    assert parts["mse"] == pytest.approx(0.0, abs=1e-10)
    assert parts["pene"] > 1.0
    loss_off, parts_off = total_loss(p, hist, v, target, kappa=1.0, psi_lim=0.2, use_pene=False)
    assert parts_off["pene"] == 0.0 and float(loss_off.detach()) < float(loss.detach())
    # the same value through the functional-style entry point used by MAML
    class B:
        pass

    b = B()
    b.target = target
    via_batch = batch_loss(p(hist, v), b, p, kappa=1.0, psi_lim=0.2)
    assert float(via_batch.detach()) == pytest.approx(float(loss.detach()))
    # within the limit there is no penalty
    hist[:, :, 3] = 1.0
    _, parts_ok = total_loss(p, hist, v, p(hist, v).detach(), kappa=1.0, psi_lim=0.2)
    assert parts_ok["pene"] == 0.0


def test_rmse_and_corr_against_numpy():
    rng = np.random.default_rng(0)
    y = rng.normal(size=500)
    y_hat = 0.7 * y + rng.normal(scale=0.3, size=500)
    assert rmse(y, y_hat) == pytest.approx(float(np.sqrt(((y - y_hat) ** 2).mean())))
    assert corr(y, y_hat) == pytest.approx(float(np.corrcoef(y, y_hat)[0, 1]))
    assert np.isnan(corr(y, np.ones(500)))
