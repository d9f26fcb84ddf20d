"""Offline training (3.3): a short run lowers the validation error; seeded; writes its metrics."""

import json

import numpy as np
import torch

from model_learner_node.config import TrainConfig
from model_learner_node.metrics import evaluate
from model_learner_node.synthetic import synthetic_split
from model_learner_node.train import dataset_hash, train_and_save, train_model
from peel_model.checkpoint import load_checkpoint
from peel_model.config import ModelConfig

TRAIN = synthetic_split(1, 16)
VAL = synthetic_split(2, 4)
TEST = synthetic_split(3, 4)
FAST = TrainConfig(lr=1e-3, epochs=6, batch_size=64, patience=10, seed=0)


def test_short_training_lowers_validation_error():
    torch.set_num_threads(1)
    res = train_model(TRAIN, VAL, model_cfg=ModelConfig(arch="ours"), train_cfg=FAST,
                      progress=False)
    curve = res.val_rmse_curve
    assert len(curve) == FAST.epochs + 1  # epoch 0 = before training
    assert res.best_val_rmse < 0.7 * curve[0]
    assert min(curve[1:]) == res.best_val_rmse
    # the returned model is the best-validation one
    assert evaluate(res.predictor, VAL)["rmse"]["all"] == res.best_val_rmse
    assert all(np.isfinite(h["train_loss"]) for h in res.history[1:])


def test_training_is_seeded():
    cfg = TrainConfig(lr=1e-3, epochs=2, batch_size=64, seed=5)
    a = train_model(TRAIN, VAL, model_cfg=ModelConfig(arch="mlp"), train_cfg=cfg, progress=False)
    b = train_model(TRAIN, VAL, model_cfg=ModelConfig(arch="mlp"), train_cfg=cfg, progress=False)
    for k, v in a.predictor.state_dict().items():
        assert torch.equal(v, b.predictor.state_dict()[k]), k
    assert a.val_rmse_curve == b.val_rmse_curve


def test_normalisation_from_training_split_only():
    res = train_model(TRAIN, VAL, model_cfg=ModelConfig(arch="mlp"),
                      train_cfg=TrainConfig(epochs=1, batch_size=64), progress=False)
    q_train = np.concatenate([t.q for t in TRAIN])
    assert float(res.predictor.in_mean[0]) == np.float32(q_train.mean())
    # synthetic psi = 0.02 * fz exactly -> the fitted pad compliance recovers it
    assert abs(float(res.predictor.pad_compliance) - 0.02) < 1e-6


def test_train_and_save_writes_checkpoint_and_test_metrics(tmp_path):
    _, metrics = train_and_save(tmp_path / "m", TRAIN, VAL, TEST,
                                  model_cfg=ModelConfig(arch="cnn-lstm"),
                                  train_cfg=TrainConfig(lr=1e-3, epochs=2, batch_size=64),
                                  progress=False)
    side = json.loads((tmp_path / "m.metrics.json").read_text())
    assert set(side["test_rmse"]) == {"fx", "fz", "all"}
    assert set(side["test_corr"]) == {"fx", "fz"}
    assert len(side["history"]) == 3
    cfg = json.loads((tmp_path / "m.json").read_text())
    assert cfg["meta"]["dataset_hash"] == dataset_hash(TRAIN, VAL, TEST)
    assert cfg["meta"]["metrics"]["test_rmse"] == side["test_rmse"]
    loaded = load_checkpoint(tmp_path / "m")
    again = evaluate(loaded, TEST)
    assert again["rmse"]["fx"] == side["test_rmse"]["fx"]
    assert again["rmse"]["fz"] == metrics["test_rmse"]["fz"]
