"""Offline learning of the forward model (paper 3.3, 4.3).

Mini-batches are trajectory slices from a :class:`~model_learner_node.replay.ReplayPool` of the
training split (3.3.1, Fig. 6); the loss is L_MSE + kappa L_PENE (Eq. 23-25); the optimiser is
Adam (4.3: lr 1e-4). After every epoch the RMSE on the validation split is measured; training
stops after ``patience`` epochs without improvement and the best-validation weights are kept
(early stopping). The test split is never looked at here: :func:`train_and_save` measures it
once, after training, and writes it beside the checkpoint.

Determinism: one seed fixes the initial weights (``torch.manual_seed``) and every slice drawn
(``numpy.random.default_rng``); there are no data-loader workers, so the result does not depend
on a number of processes.
"""

from __future__ import annotations

import copy
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from peel_model.checkpoint import atomic_write_json, checkpoint_paths, save_checkpoint
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, fit_normalization
from peel_model.windows import stack_windows
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import Trajectory

from .config import TrainConfig
from .devices import resolve_device
from .losses import total_loss
from .metrics import evaluate_windows, persistence_metrics
from .replay import ReplayPool


@dataclass
class TrainResult:
    """A trained predictor (best validation epoch) and its learning curve."""

    predictor: ForcePredictor
    history: list[dict[str, float]] = field(default_factory=list)
    best_epoch: int = 0
    best_val_rmse: float = math.inf
    stopped_early: bool = False

    @property
    def val_rmse_curve(self) -> list[float]:
        return [h["val_rmse"] for h in self.history]


def dataset_hash(*splits: Sequence[Trajectory]) -> str:
    """SHA-256 over the per-sample arrays of every trajectory, split by split (in order)."""
    h = hashlib.sha256()
    for i, split in enumerate(splits):
        h.update(f"split{i}:{len(split)}".encode())
        for t in split:
            h.update(np.ascontiguousarray(t.as_array(), dtype="<f8").tobytes())
    return h.hexdigest()


def _windows_per_epoch(pool: ReplayPool, cfg: TrainConfig, h: int) -> int:
    """Slices per epoch: ``samples_per_epoch`` or as many as cover every training window once."""
    if cfg.samples_per_epoch > 0:
        return cfg.samples_per_epoch
    per_slice = cfg.slice_len - h
    return max(cfg.batch_size, math.ceil(pool.n_slices(h + 1) / per_slice))


def train_model(
    train: Sequence[Trajectory],
    val: Sequence[Trajectory],
    *,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    use_pene: bool = True,
    init: ForcePredictor | None = None,
    device: str | torch.device = "cpu",
    progress: bool = True,
    desc: str = "train",
) -> TrainResult:
    """Train a forward model; ``init`` fine-tunes a copy of it (its normalisation is kept)."""
    if not train:
        raise PeelError("the training split has no trajectories")
    if not val:
        raise PeelError("the validation split has no trajectories")
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    torch.manual_seed(train_cfg.seed)
    rng = np.random.default_rng(train_cfg.seed)
    if init is not None:
        predictor = copy.deepcopy(init).to(dev)
    else:
        norm = fit_normalization(train, model_cfg.h,
                                 default_compliance=train_cfg.pad_compliance_mm_per_n)
        predictor = ForcePredictor(model_cfg, norm).to(dev)
    h = predictor.h
    slice_len = max(train_cfg.slice_len, h + 1)
    pool = ReplayPool(train, pad_front=h - 1)
    if pool.n_slices(slice_len) == 0:
        raise PeelError(f"no training trajectory is long enough for slices of {slice_len} samples")
    val_win = stack_windows(val, h)
    if len(val_win) == 0:
        raise PeelError("the validation split has no usable samples (trajectories too short)")
    per_epoch = _windows_per_epoch(pool, replace(train_cfg, slice_len=slice_len), h)
    n_batches = max(1, math.ceil(per_epoch / train_cfg.batch_size))
    opt = torch.optim.Adam(predictor.parameters(), lr=train_cfg.lr,
                           weight_decay=train_cfg.weight_decay)
    result = TrainResult(predictor=predictor)
    best_state = copy.deepcopy(predictor.state_dict())
    start = evaluate_windows(predictor, val_win)
    result.best_val_rmse = start["rmse"]["all"]
    result.history.append({"epoch": 0, "train_loss": float("nan"), "train_mse": float("nan"),
                           "train_pene": float("nan"), "val_rmse": start["rmse"]["all"],
                           "val_rmse_fx": start["rmse"]["fx"], "val_rmse_fz": start["rmse"]["fz"]})
    bad = 0
    bar = tqdm(range(1, train_cfg.epochs + 1), desc=desc, disable=not progress, leave=False,
               dynamic_ncols=True)
    for epoch in bar:
        predictor.train()
        sums = {"loss": 0.0, "mse": 0.0, "pene": 0.0}
        for _ in range(n_batches):
            win = pool.sample_slices(train_cfg.batch_size, slice_len, rng).windows(h).to_torch(dev)
            loss, parts = total_loss(predictor, win.hist, win.v_next, win.f_next,
                                     kappa=train_cfg.kappa, psi_lim=train_cfg.psi_lim_mm,
                                     use_pene=use_pene)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if train_cfg.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(predictor.parameters(), train_cfg.grad_clip)
            opt.step()
            sums["loss"] += float(loss.detach())
            sums["mse"] += parts["mse"]
            sums["pene"] += parts["pene"]
        m = evaluate_windows(predictor, val_win)
        rec = {"epoch": epoch, "train_loss": sums["loss"] / n_batches,
               "train_mse": sums["mse"] / n_batches, "train_pene": sums["pene"] / n_batches,
               "val_rmse": m["rmse"]["all"], "val_rmse_fx": m["rmse"]["fx"],
               "val_rmse_fz": m["rmse"]["fz"]}
        result.history.append(rec)
        if not math.isfinite(rec["train_loss"]):
            raise PeelError(f"training diverged at epoch {epoch} (non-finite loss)")
        if m["rmse"]["all"] < result.best_val_rmse:
            result.best_val_rmse = m["rmse"]["all"]
            result.best_epoch = epoch
            best_state = copy.deepcopy(predictor.state_dict())
            bad = 0
        else:
            bad += 1
        bar.set_postfix(loss=f"{rec['train_loss']:.4f}", val_rmse=f"{m['rmse']['all']:.4f}",
                        best=result.best_epoch)
        if bad >= train_cfg.patience:
            result.stopped_early = True
            break
    bar.close()
    predictor.load_state_dict(best_state)
    predictor.eval()
    return result


def train_and_save(
    out: str | Path,
    train: Sequence[Trajectory],
    val: Sequence[Trajectory],
    test: Sequence[Trajectory],
    *,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    use_pene: bool = True,
    init: ForcePredictor | None = None,
    device: str = "cpu",
    progress: bool = True,
    extra_meta: dict[str, Any] | None = None,
    test_label: str = "test",
) -> tuple[TrainResult, dict[str, Any]]:
    """Train, evaluate once on ``test``, and write the checkpoint + ``<name>.metrics.json``."""
    result = train_model(train, val, model_cfg=model_cfg, train_cfg=train_cfg, use_pene=use_pene,
                         init=init, device=device, progress=progress,
                         desc=f"train {model_cfg.arch}")
    test_win = stack_windows(test, result.predictor.h)
    if len(test_win) == 0:
        raise PeelError(f"the {test_label} split has no usable samples")
    tm = evaluate_windows(result.predictor, test_win)
    by_set: dict[str, dict[str, float]] = {}
    for key in sorted({str(t.meta.get("set")) for t in test if "set" in t.meta}):
        part = [t for t in test if str(t.meta.get("set")) == key]
        pm = evaluate_windows(result.predictor, stack_windows(part, result.predictor.h))
        by_set[key] = {**pm["rmse"], "n_trajectories": len(part), "n_samples": pm["n_samples"]}
    metrics = {
        "split": test_label,
        "test_rmse": {k: tm["rmse"][k] for k in ("fx", "fz", "all")},
        "test_corr": dict(tm["corr"]),
        "n_test_samples": tm["n_samples"],
        "persistence_rmse": persistence_metrics(test_win)["rmse"],
        "test_rmse_by_set": by_set,
        "best_epoch": result.best_epoch,
        "best_val_rmse": result.best_val_rmse,
        "epochs_run": len(result.history) - 1,
        "stopped_early": result.stopped_early,
    }
    meta = {
        "dataset_hash": dataset_hash(train, val, test),
        "n_trajectories": {"train": len(train), "val": len(val), test_label: len(test)},
        "use_pene": use_pene,
        "train_config": train_cfg.to_json(),
        "metrics": metrics,
        **(extra_meta or {}),
    }
    result.predictor.cpu()
    st_path = save_checkpoint(out, result.predictor, meta)
    atomic_write_json(output_paths(out)[2],
                      {**metrics, "history": result.history, "checkpoint": st_path.name})
    return result, metrics


def output_paths(out: str | Path) -> list[Path]:
    """What :func:`train_and_save` writes: ``<name>.safetensors``, ``.json``, ``.metrics.json``."""
    st_path, js_path = checkpoint_paths(out)
    stem = st_path.with_suffix("")
    return [st_path, js_path, stem.with_name(stem.name + ".metrics.json")]
