"""The model swap of ``peel_planner_node`` over its SetParameters service (docs/graph.md).

A real planner process on rclpy; this test process is the client (rclpy, the standard
``rcl_interfaces/srv/SetParameters``). Corrupted,
truncated, mismatched, non-finite and pickled weights are refused with a reason and the running
model (``/peel/model_version``) stays; a good checkpoint is accepted and its version published:
the planner's next version, whatever the file is called (``model_v0007`` does not make it 7),
with the model's identity on ``/peel/model_info``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from graph_helpers import node_env
from safetensors.torch import load_file, save_file

from peel_model.checkpoint import load_checkpoint, save_checkpoint
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor
from peel_planner_node.model_check import validate_model

pytestmark = pytest.mark.process  # starts processes or real-time I/O: scripts/flaky.sh


def _model(tmp: Path) -> Path:
    """A freshly initialised (seeded) model: the running and the reference checkpoint."""
    path = tmp / "init.safetensors"
    if not path.exists():
        torch.manual_seed(0)
        save_checkpoint(path, ForcePredictor(ModelConfig()))
    return path


def _good(tmp: Path, name: str) -> Path:
    return save_checkpoint(tmp / name, load_checkpoint(_model(tmp)))


def _bad_files(tmp: Path) -> dict[str, tuple[Path, str]]:
    """name -> (path, a word the refusal reason must contain)."""
    out: dict[str, tuple[Path, str]] = {}
    garbage = tmp / "garbage.safetensors"
    garbage.write_bytes(os.urandom(512))
    shutil.copy(_model(tmp).with_suffix(".json"), tmp / "garbage.json")
    out["garbage"] = (garbage, "garbage")
    trunc = _good(tmp, "trunc")
    trunc.write_bytes(trunc.read_bytes()[:-100])
    out["truncated"] = (trunc, "truncated")
    # another architecture's weights under this config: tensor names / shapes differ
    other = save_checkpoint(tmp / "other", ForcePredictor(ModelConfig(arch="mlp")))
    mism = _good(tmp, "mismatch")
    mism.write_bytes(other.read_bytes())
    cfg = json.loads(mism.with_suffix(".json").read_text())
    cfg["safetensors_bytes"] = other.stat().st_size
    cfg["safetensors_sha256"] = json.loads(other.with_suffix(".json").read_text())[
        "safetensors_sha256"]
    mism.with_suffix(".json").write_text(json.dumps(cfg))
    out["mismatched"] = (mism, "mismatch")
    # a different history length h than the running model
    h6 = save_checkpoint(tmp / "h6", ForcePredictor(ModelConfig(h=6)))
    out["other_h"] = (h6, "h = 6")
    # finite file, NaN weights
    nan = tmp / "nan.safetensors"
    tensors = load_file(str(_model(tmp)))
    key = next(k for k, v in tensors.items() if v.is_floating_point() and v.numel() > 1)
    tensors[key] = torch.full_like(tensors[key], float("nan"))
    save_checkpoint(nan, load_checkpoint(_model(tmp)))
    save_file(tensors, str(nan))
    cfg = json.loads(nan.with_suffix(".json").read_text())
    blob = nan.read_bytes()
    cfg["safetensors_bytes"], cfg["safetensors_sha256"] = len(blob), hashlib.sha256(blob).hexdigest()
    nan.with_suffix(".json").write_text(json.dumps(cfg))
    out["nan"] = (nan, "non-finite")
    # a pickle is never loaded
    pkl = tmp / "model.pt"
    pkl.write_bytes(pickle.dumps({"weights": [1, 2, 3]}))
    out["pickle"] = (pkl, ".safetensors")
    out["missing"] = (tmp / "nope.safetensors", "cannot read")
    return out


def test_validate_model_refuses_bad_files(tmp_path: Path) -> None:
    from peel_msgs_py.errors import PeelError

    for name, (path, word) in _bad_files(tmp_path).items():
        with pytest.raises(PeelError) as exc:
            validate_model(path, None, 8, 10)
        assert word.lower() in str(exc.value).lower(), (name, str(exc.value))
    assert validate_model(_good(tmp_path, "ok"), None, 8, 10).h == 10


def test_swap_service_refuses_with_reason_and_keeps_model(
        tmp_path: Path, ros_domain: str) -> None:
    bad = _bad_files(tmp_path)
    good = _good(tmp_path, "model_v0007")
    env = node_env()
    log = (tmp_path / "planner.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "peel_planner_node.node", "--ros-args",
                             "-p", "mppi.n_samples:=8", "-p", "mppi.horizon:=2",
                             "-p", "node.min_cmd_subscribers:=0",
                             "-p", f"model.path:={_model(tmp_path)}"],
                            env=env, stdout=log, stderr=subprocess.STDOUT)
    import rclpy
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from rclpy.node import Node
    from std_msgs.msg import Int64, String

    from peel_msgs_py import topics

    rclpy.init(args=None)
    node = Node("swap_test")
    versions: list[int] = []
    infos: list[dict] = []
    node.create_subscription(Int64, topics.MODEL_VERSION, lambda m: versions.append(int(m.data)),
                             topics.qos_profile(topics.MODEL_VERSION, subscriber=True))
    node.create_subscription(String, topics.MODEL_INFO, lambda m: infos.append(json.loads(m.data)),
                             topics.qos_profile(topics.MODEL_INFO, subscriber=True))
    client = node.create_client(SetParameters, "/peel_planner_node/set_parameters")

    def spin_until(cond, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while not cond() and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        return cond()

    def swap(path: Path) -> tuple[bool, str]:
        req = SetParameters.Request()
        req.parameters = [Parameter(name="model.path", value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=str(path)))]
        fut = client.call_async(req)
        assert spin_until(fut.done, 120), "no answer from the planner"
        res = fut.result().results[0]
        return bool(res.successful), str(res.reason)

    try:
        assert client.wait_for_service(timeout_sec=60), (tmp_path / "planner.log").read_text()
        assert spin_until(lambda: versions == [0], 120), versions
        for name, (path, word) in bad.items():
            ok, reason = swap(path)
            assert not ok, name
            assert "refused" in reason and word.lower() in reason.lower(), (name, reason)
        ok, reason = swap(good)
        assert ok, reason
        assert spin_until(lambda: versions[-1:] == [1] and len(infos) == 2, 120), versions
        assert versions == [0, 1]  # nothing changed on the refusals; no number from the name
        sha = json.loads(good.with_suffix(".json").read_text())["safetensors_sha256"]
        assert infos[1] == {"version": 1, "sha256": sha, "path": str(good), "producer": None,
                            "task": None}
        assert infos[0]["version"] == 0 and infos[0]["path"] == str(_model(tmp_path))
        assert proc.poll() is None  # the planner survived every bad file
    finally:
        node.destroy_node()
        rclpy.shutdown()
        proc.send_signal(2)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
