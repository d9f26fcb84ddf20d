"""``peel train --from-bags``: fine-tuning from trajectories recorded in a real MCAP bag."""

import json
import subprocess
import sys

import ros_msgs as M
import torch

from model_learner_node.synthetic import synthetic_split
from peel_bag.bag import BagWriter
from peel_model.checkpoint import load_checkpoint, save_checkpoint
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, fit_normalization
from peel_msgs_py import topics as T
from peel_msgs_py.ros.messages import trajectory_msg


def write_bag(path, trajs):
    with BagWriter(path) as bag:
        bag.add_topic(T.TRAJECTORY, T.topic(T.TRAJECTORY).type, [T.topic(T.TRAJECTORY).qos])
        for i, traj in enumerate(trajs):
            bag.write(T.TRAJECTORY, M.serialize(trajectory_msg(traj)),
                      1_700_000_000_000_000_000 + i * 10**9)


def peel(*args):
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", *args],
                          capture_output=True, text=True, timeout=300)


def test_fine_tune_from_bags(tmp_path):
    trajs = synthetic_split(7, 6)
    write_bag(tmp_path / "run1", trajs[:4])
    write_bag(tmp_path / "run2", trajs[4:])
    torch.manual_seed(0)
    init = ForcePredictor(ModelConfig(arch="mlp"), fit_normalization(synthetic_split(8, 4), 10))
    save_checkpoint(tmp_path / "init", init)
    r = peel("train", "--from-bags", str(tmp_path / "run1"), str(tmp_path / "run2"),
             "--init", str(tmp_path / "init.safetensors"), "--out", str(tmp_path / "tuned"),
             "--epochs", "3", "--lr", "1e-3", "--quiet", "--threads", "1")
    assert r.returncode == 0, r.stderr
    printed = json.loads(r.stdout)
    assert printed["split"] == "holdout"
    tuned = load_checkpoint(tmp_path / "tuned")
    cfg = json.loads((tmp_path / "tuned.json").read_text())
    assert cfg["meta"]["n_trajectories"] == {"train": 5, "val": 1, "holdout": 1}
    assert cfg["meta"]["bags"] == [str(tmp_path / "run1"), str(tmp_path / "run2")]
    # normalisation kept from --init, weights changed by training
    assert torch.equal(tuned.in_mean, init.in_mean)
    assert not torch.equal(tuned.state_dict()["body.regressor.0.weight"],
                           init.state_dict()["body.regressor.0.weight"])
    side = json.loads((tmp_path / "tuned.metrics.json").read_text())
    assert side["test_rmse"] == printed["test_rmse"]
    assert [h["epoch"] for h in side["history"]] == [0, 1, 2, 3]


def test_bad_input_exits_2_with_one_line(tmp_path):
    r = peel("train", "--from-bags", str(tmp_path / "nope"), "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert "--init" in r.stderr and "Traceback" not in r.stderr
    (tmp_path / "bad.json").write_text("{")
    r = peel("train", "--from-bags", str(tmp_path / "nope"), "--init", str(tmp_path / "bad"),
             "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert "not valid JSON" in r.stderr and len(r.stderr.strip().splitlines()) == 1
