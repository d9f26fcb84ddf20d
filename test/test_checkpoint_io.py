"""Checkpoints: safetensors + JSON, bit-exact round trip, strict refusal of bad files."""

import json
import shutil

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import load_file as np_load_file

from peel_model.checkpoint import (
    checkpoint_paths,
    load_checkpoint,
    read_checkpoint_config,
    save_checkpoint,
)
from peel_model.config import ModelConfig
from peel_model.predictor import ForcePredictor, Normalization
from peel_msgs_py.errors import CheckpointError

NORM = Normalization(in_mean=(12.0, 1.5, 2.0, 3.0), in_std=(7.0, 1.1, 0.9, 1.3),
                     out_mean=(0.01, -0.02), out_std=(0.3, 0.4), pad_compliance_mm_per_n=0.017)


def make(arch="ours", seed=0, **kw):
    torch.manual_seed(seed)
    return ForcePredictor(ModelConfig(arch=arch, **kw), NORM)


@pytest.mark.parametrize("arch", ["ours", "mlp", "cnn-lstm"])
def test_round_trip_bit_exact(tmp_path, arch):
    p = make(arch)
    st = save_checkpoint(tmp_path / "m", p, {"dataset_hash": "abc", "metrics": {"x": 1.5}})
    assert st.name == "m.safetensors" and (tmp_path / "m.json").is_file()
    q = load_checkpoint(tmp_path / "m.safetensors")
    sd_p, sd_q = p.state_dict(), q.state_dict()
    assert sd_p.keys() == sd_q.keys()
    for k in sd_p:
        assert sd_q[k].dtype == sd_p[k].dtype
        assert torch.equal(sd_p[k], sd_q[k]), k
    hist, v = torch.randn(5, 10, 4), torch.randn(5)
    p.eval()
    assert torch.equal(p(hist, v), q(hist, v))
    assert q.arch == arch and q.h == 10 and q.normalization == p.normalization
    # read back by independent readers: json and safetensors.numpy
    cfg = json.loads((tmp_path / "m.json").read_text())
    assert cfg["arch"] == arch and cfg["h"] == 10 and cfg["meta"]["dataset_hash"] == "abc"
    assert cfg["normalization"]["in_mean"] == list(p.normalization.in_mean)
    arrays = np_load_file(str(tmp_path / "m.safetensors"))
    assert set(arrays) == set(cfg["tensors"])
    for k, a in arrays.items():
        assert list(a.shape) == cfg["tensors"][k]["shape"]
        np.testing.assert_array_equal(a, sd_p[k].numpy())


def test_the_same_model_saved_twice_is_the_same_file(tmp_path):
    """The file's SHA-256 is the model's identity: every save of the same model and meta gives
    the same bytes (safetensors itself writes its metadata in hash-map order)."""
    p = make("ours")
    blobs = {(save_checkpoint(tmp_path / f"m{i}", p, {"x": 1}).read_bytes()) for i in range(8)}
    assert len(blobs) == 1
    with safe_open(str(tmp_path / "m0.safetensors"), framework="np") as f:  # still a valid file
        assert f.metadata() == {"format": "peel-forward-model", "format_version": "1"}
        for k, v in p.state_dict().items():
            np.testing.assert_array_equal(f.get_tensor(k), v.numpy())
    cfg = json.loads((tmp_path / "m0.json").read_text())
    assert cfg["safetensors_bytes"] == len(next(iter(blobs)))
    q = load_checkpoint(tmp_path / "m3")
    assert all(torch.equal(a, b) for a, b in zip(q.state_dict().values(),
                                                  p.state_dict().values(), strict=True))


def test_any_suffix_names_the_same_checkpoint(tmp_path):
    save_checkpoint(tmp_path / "m.json", make("mlp"))
    for name in ("m", "m.json", "m.safetensors"):
        assert load_checkpoint(tmp_path / name).arch == "mlp"


def test_truncated_weights_refused(tmp_path):
    save_checkpoint(tmp_path / "m", make())
    st, _ = checkpoint_paths(tmp_path / "m")
    data = st.read_bytes()
    st.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(st)


def test_truncated_config_refused(tmp_path):
    save_checkpoint(tmp_path / "m", make())
    js = tmp_path / "m.json"
    js.write_text(js.read_text()[:200])
    with pytest.raises(CheckpointError, match="not valid JSON"):
        load_checkpoint(js)


def test_corrupted_weights_refused(tmp_path):
    save_checkpoint(tmp_path / "m", make())
    st = tmp_path / "m.safetensors"
    data = bytearray(st.read_bytes())
    data[-5] ^= 0xFF
    st.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="SHA-256"):
        load_checkpoint(st)


def test_weights_of_another_checkpoint_refused(tmp_path):
    save_checkpoint(tmp_path / "a", make("ours"))
    save_checkpoint(tmp_path / "b", make("mlp"))
    shutil.copy(tmp_path / "b.safetensors", tmp_path / "a.safetensors")
    with pytest.raises(CheckpointError, match="bytes but its config records"):
        load_checkpoint(tmp_path / "a")


def edit_config(path, fn):
    cfg = json.loads(path.read_text())
    fn(cfg)
    path.write_text(json.dumps(cfg))


def test_shape_mismatch_with_architecture_refused(tmp_path):
    """A consistent file pair whose config describes another network (h=12, not 10)."""
    save_checkpoint(tmp_path / "m", make("mlp"))

    def to_h12(cfg):
        cfg["h"] = 12
        cfg["model_config"]["h"] = 12

    edit_config(tmp_path / "m.json", to_h12)
    with pytest.raises(CheckpointError, match=r"'body.regressor.0.weight'.*h=12 needs \[128, 49\]"):
        load_checkpoint(tmp_path / "m")


def test_recorded_shape_mismatch_refused(tmp_path):
    save_checkpoint(tmp_path / "m", make("ours"))
    edit_config(tmp_path / "m.json",
                lambda c: c["tensors"]["in_mean"].update(shape=[5]))
    with pytest.raises(CheckpointError, match=r"'in_mean'.*config records float32 \[5\]"):
        load_checkpoint(tmp_path / "m")


def test_missing_tensor_in_config_refused(tmp_path):
    save_checkpoint(tmp_path / "m", make("ours"))
    edit_config(tmp_path / "m.json", lambda c: c["tensors"].pop("out_std"))
    with pytest.raises(CheckpointError, match=r"the config does not match.*missing \['out_std'\]"):
        load_checkpoint(tmp_path / "m")


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("format_version", 99, "format_version 99 is not supported"),
        ("format", "something-else", "format is 'something-else'"),
        ("arch", "transformer", "arch 'transformer' is not one of"),
    ],
)
def test_wrong_format_or_version_refused(tmp_path, field, value, message):
    save_checkpoint(tmp_path / "m", make())
    edit_config(tmp_path / "m.json", lambda c: c.update({field: value}))
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(tmp_path / "m")
    with pytest.raises(CheckpointError, match=message):
        read_checkpoint_config(tmp_path / "m")


def test_missing_files_refused(tmp_path):
    with pytest.raises(CheckpointError, match="cannot read checkpoint config"):
        load_checkpoint(tmp_path / "nothing")
    save_checkpoint(tmp_path / "m", make())
    (tmp_path / "m.safetensors").unlink()
    with pytest.raises(CheckpointError, match="cannot read checkpoint weights"):
        load_checkpoint(tmp_path / "m")


def test_save_is_atomic_no_temp_files_left(tmp_path):
    save_checkpoint(tmp_path / "m", make())
    save_checkpoint(tmp_path / "m", make(seed=1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.safetensors"]
    assert torch.equal(load_checkpoint(tmp_path / "m").state_dict()["body.conv.convs.0.weight"],
                       make(seed=1).state_dict()["body.conv.convs.0.weight"])
