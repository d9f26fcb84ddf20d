"""`peel dataset`: determinism over workers, Parquet read back by pyarrow, resume, refusal."""

import json
import subprocess
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from peel_msgs_py.errors import PeelError
from peel_sim_node.config import load_sim_config
from peel_sim_node.dataset import config_hash, generate_dataset, load_split, split_of_sets

CFG = load_sim_config()
PEEL = [sys.executable, "-m", "peel_bringup.cli"]


def run_cli(*args):
    return subprocess.run([*PEEL, "dataset", *args], capture_output=True, text=True, timeout=300)


def shard_files(d):
    return sorted(p.relative_to(d) for p in d.rglob("*.parquet"))


def test_same_seed_same_bytes_for_1_and_2_workers(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    r1 = run_cli("--param-sets", "4", "--per-set", "2", "--out", str(a), "--workers", "1",
                 "--seed", "7")
    r2 = run_cli("--param-sets", "4", "--per-set", "2", "--out", str(b), "--workers", "2",
                 "--seed", "7", "--no-progress")
    assert r1.returncode == 0, r1.stderr
    assert r2.returncode == 0, r2.stderr
    assert "peel dataset" in r1.stderr  # tqdm progress bar
    files = shard_files(a)
    assert len(files) == 4 and files == shard_files(b)
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes()
    # read back with pyarrow alone: columns, units and per-trajectory params/outcome
    t = pq.read_table(a / files[0])
    meta = json.loads(t.schema.metadata[b"peel"])
    assert meta["units"]["q"] == "mm" and meta["units"]["fx"] == "N"
    assert meta["seed"] == 7 and "code_version" in meta
    assert len(meta["trajectories"]) == 2
    info = meta["trajectories"][0]
    assert info["outcome"] in ("done", "safety_stop", "timeout")
    assert {"friction", "stiffness", "damping"} <= set(info["params"])
    assert set(t.column_names) >= {"traj", "k", "t", "q", "v", "u", "fx", "fz", "psi"}
    # load_split gives Trajectory objects matching the table
    man = json.loads((a / "dataset.json").read_text())
    n_train = man["splits"]["train"]["trajectories"]
    trajs = load_split(a, "train")
    assert len(trajs) == n_train
    sizes = sum(len(x) for s in ("train", "val", "test") for x in load_split(a, s))
    assert sizes == sum(pq.read_table(a / f).num_rows for f in files)
    # a different seed gives different data
    c = tmp_path / "c"
    generate_dataset(CFG, c, param_sets=1, per_set=2, seed=8, progress=False)
    assert load_split(c, split_of_sets(1, 8)[0])[0].params != trajs[0].params


def test_resume_regenerates_missing_and_broken_shards(tmp_path):
    d = tmp_path / "d"
    generate_dataset(CFG, d, param_sets=3, per_set=1, seed=1, progress=False)
    files = shard_files(d)
    ref = {f: (d / f).read_bytes() for f in files}
    (d / files[0]).unlink()
    (d / files[1]).write_bytes(b"truncated")
    (d / "dataset.json").unlink()  # as after an interruption
    with pytest.raises(PeelError, match="complete"):
        load_split(d, "train")
    generate_dataset(CFG, d, param_sets=3, per_set=1, seed=1, progress=False)
    assert {f: (d / f).read_bytes() for f in shard_files(d)} == ref
    # resuming with other settings is refused
    with pytest.raises(PeelError, match="other settings"):
        generate_dataset(CFG, d, param_sets=3, per_set=1, seed=2, progress=False)


def test_refuses_existing_non_dataset_dir(tmp_path):
    d = tmp_path / "mine"
    d.mkdir()
    (d / "notes.txt").write_text("keep me")
    r = run_cli("--param-sets", "1", "--per-set", "1", "--out", str(d))
    assert r.returncode == 2
    assert "not a peel dataset" in r.stderr and "--out" in r.stderr
    assert sorted(p.name for p in d.iterdir()) == ["notes.txt"]


def test_split_80_10_10_by_parameter_set():
    s = split_of_sets(1000, 0)
    assert (s.count("train"), s.count("val"), s.count("test")) == (800, 100, 100)
    assert split_of_sets(1000, 0) == s and split_of_sets(1000, 1) != s


def test_plant_source_dataset(tmp_path):
    d = tmp_path / "p"
    generate_dataset(CFG, d, param_sets=1, per_set=2, seed=0, source="plant", progress=False)
    tr = load_split(d, split_of_sets(1, 0)[0])
    assert tr[0].meta["source"] == "plant"
    assert np.isfinite(tr[0].fx).all()


def test_plant_settings_do_not_invalidate_a_sim_dataset(tmp_path):
    d = tmp_path / "s"
    generate_dataset(CFG, d, param_sets=1, per_set=1, seed=4, progress=False)
    ref = {f: (d / f).read_bytes() for f in shard_files(d)}
    plant_tuned = load_sim_config({"plant.residual_vacuum_n": 1.0})
    generate_dataset(plant_tuned, d, param_sets=1, per_set=1, seed=4, progress=False)
    assert {f: (d / f).read_bytes() for f in shard_files(d)} == ref
    sim_changed = load_sim_config({"load.base_n": 1.4})
    with pytest.raises(PeelError, match="config_hash"):
        generate_dataset(sim_changed, d, param_sets=1, per_set=1, seed=4, progress=False)


def test_the_slowdown_zone_shapes_the_dataset_hash_only_when_it_is_enabled():
    """Eq. M6 off leaves every command as sent, so its other settings cannot change the data;
    on, it can, and the hash (the resume check and the shipped model's provenance) sees it."""
    off = config_hash(CFG, "sim")
    assert config_hash(load_sim_config({"safety.slowdown.start_n": 18.0}), "sim") == off
    on = load_sim_config({"safety.slowdown.enabled": True})
    assert config_hash(on, "sim") != off
    assert config_hash(load_sim_config({"safety.slowdown.enabled": True,
                                        "safety.slowdown.start_n": 18.0}), "sim") != \
        config_hash(on, "sim")
