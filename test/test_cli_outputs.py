"""The shared command-line helpers: argument types, the top-level handler, output locations,
device names and the dataset check."""

from __future__ import annotations

import argparse
import json
import shutil

import pytest
import torch

from model_learner_node.devices import check_device, device_arg
from peel_msgs_py.cliargs import (
    ArgumentParser,
    UsageError,
    float_list,
    int_list,
    nonnegative_int,
    positive_float,
    positive_int,
    run_main,
)
from peel_msgs_py.errors import PeelError
from peel_msgs_py.outputs import (
    RUN_MARKER,
    OutputDir,
    check_location,
    check_new_path,
    check_output_files,
)
from peel_sim_node.config import load_sim_config
from peel_sim_node.dataset import check_dataset, generate_dataset, load_split


@pytest.mark.parametrize(("kind", "text"), [
    (positive_int, "0"), (positive_int, "-1"), (positive_int, "1.5"), (nonnegative_int, "-1"),
    (positive_float, "nan"), (positive_float, "inf"), (positive_float, "-inf"),
    (positive_float, "0"), (positive_float, "-1e-3"), (positive_float, "fast"),
    (float_list(0.0, min_open=True), "0.1,inf"), (float_list(0.0, min_open=True), "0.1,nan"),
    (float_list(0.0, min_open=True), ","), (int_list(0), "1,-2"), (int_list(0), "1,x"),
])
def test_argument_types_refuse(kind, text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        kind(text)


def test_argument_types_accept() -> None:
    assert positive_int("3") == 3 and nonnegative_int("0") == 0
    assert positive_float("1e-4") == 1e-4
    assert float_list(0.0, min_open=True)("0.1, 0.5") == (0.1, 0.5)
    assert int_list(0)("0,1,2") == (0, 1, 2)


def test_usage_errors_are_one_line_through_run_main(capsys) -> None:
    p = ArgumentParser(prog="peel thing")
    p.add_argument("--lr", type=positive_float, required=True)

    def main(argv: list[str]) -> int:
        p.parse_args(argv)
        return 0

    with pytest.raises(UsageError, match="--lr"):
        p.parse_args(["--lr", "nan"])
    assert run_main("peel thing", main, ["--lr", "nan"]) == 2
    assert run_main("peel thing", main, ["--lr", "1", "--bogus"]) == 2
    assert run_main("peel thing", main, []) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("peel thing: error: ") for line in err)
    assert "expected a finite number, got 'nan'" in err[0]
    assert "unrecognized arguments: --bogus" in err[1]
    assert "required: --lr" in err[2]
    with pytest.raises(SystemExit) as help_exit:  # --help still prints the usage and exits 0
        run_main("peel thing", main, ["--help"])
    assert help_exit.value.code == 0


def test_run_main_maps_errors_to_one_line(capsys) -> None:
    def bad_input(argv: list[str]) -> int:
        raise PeelError("parameter file x.yaml is not valid UTF-8")

    def disk(argv: list[str]) -> int:
        raise OSError(28, "No space left on device", "/data/out.bin")

    assert run_main("peel x", bad_input, []) == 2
    assert run_main("peel x", disk, []) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["peel x: error: parameter file x.yaml is not valid UTF-8",
                   "peel x: error: cannot complete /data/out.bin: No space left on device"]


@pytest.mark.parametrize("path", ["/proc/x", "/proc/self/y/z", "/sys/peel"])
def test_pseudo_file_systems_are_refused(path: str) -> None:
    with pytest.raises(PeelError, match="kernel interface"):
        check_location(path)


def test_a_file_in_the_way_is_refused(tmp_path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(PeelError, match="is a file, not a folder"):
        check_location(tmp_path / "f" / "sub" / "out")
    with pytest.raises(PeelError, match="already exists"):
        check_new_path(tmp_path / "f", "--record")
    check_location(tmp_path / "new" / "deeper")  # creatable
    assert not (tmp_path / "new").exists()  # the probe leaves nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]


def test_output_files_need_force_to_replace(tmp_path) -> None:
    a, b = tmp_path / "m.safetensors", tmp_path / "m.json"
    check_output_files([a, b])
    a.write_bytes(b"x")
    with pytest.raises(PeelError, match=r"already exists.*--force"):
        check_output_files([a, b])
    check_output_files([a, b], force=True)
    (tmp_path / "d.json").mkdir()
    with pytest.raises(PeelError, match="is a folder"):
        check_output_files([tmp_path / "d.json"], force=True)


def test_output_dir_lifecycle(tmp_path) -> None:
    out = tmp_path / "a" / "b" / "run"
    with OutputDir(out, command="peel figures") as d:
        assert d == out and json.loads((d / RUN_MARKER).read_text())["command"] == "peel figures"
        (d / "figures.json").write_text("{}")
    # an earlier run: refused, or replaced (only) with --force
    with pytest.raises(PeelError, match=r"earlier 'peel figures' run.*--force"):
        OutputDir(out, command="peel figures")
    forced = OutputDir(out, command="peel graph", force=True)
    assert (out / "figures.json").exists()  # checking deletes nothing
    with forced:
        assert sorted(p.name for p in out.iterdir()) == [RUN_MARKER]
    # a failure before anything is written removes the folder and the parents it created
    fresh = tmp_path / "x" / "y" / "run"
    with pytest.raises(RuntimeError), OutputDir(fresh, command="peel graph"):
        raise RuntimeError("boom")
    assert not (tmp_path / "x").exists()
    # ... but an existing empty folder stays, without a marker
    (tmp_path / "empty").mkdir()
    with pytest.raises(RuntimeError), OutputDir(tmp_path / "empty", command="peel graph"):
        raise RuntimeError("boom")
    assert (tmp_path / "empty").is_dir() and not any((tmp_path / "empty").iterdir())


def test_output_dir_relative_path(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    with OutputDir("runs/x", command="peel soak") as d:
        assert (tmp_path / "runs" / "x" / RUN_MARKER).is_file() and str(d) == "runs/x"
    with pytest.raises(RuntimeError), OutputDir("new/y", command="peel soak"):
        raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]


def test_output_dir_never_touches_foreign_files(tmp_path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    mtime = tmp_path.stat().st_mtime_ns
    for force in (False, True):
        with pytest.raises(PeelError, match="not empty and holds no peel run"):
            OutputDir(tmp_path, command="peel graph", force=force)
    assert (tmp_path / "notes.txt").read_text() == "mine"
    assert tmp_path.stat().st_mtime_ns == mtime  # not even a probe was created in it
    (tmp_path / "notes.txt").unlink()
    (tmp_path / RUN_MARKER).write_text("{}")  # a run killed before it wrote anything
    OutputDir(tmp_path, command="peel graph")  # counts as empty
    with pytest.raises(PeelError, match="is an existing file"):
        OutputDir(tmp_path / RUN_MARKER, command="peel graph")


def test_device_names_are_checked_against_torch() -> None:
    assert check_device("cpu").type == "cpu" and check_device("auto").type in ("cpu", "cuda")
    for name in ("tpu", "gpu", "cuda:x"):
        with pytest.raises(PeelError, match="unknown device"):
            check_device(name)
    with pytest.raises(PeelError, match="not supported"):
        check_device("meta")
    with pytest.raises(PeelError, match="CUDA"):
        check_device("cuda:99")
    if not torch.cuda.is_available():
        with pytest.raises(argparse.ArgumentTypeError, match="CUDA is not available"):
            device_arg("cuda")


def test_truncated_or_missing_shard_is_named(tmp_path) -> None:
    ds = tmp_path / "ds"
    generate_dataset(load_sim_config(), ds, param_sets=3, per_set=1, progress=False)
    assert check_dataset(ds)["param_sets"] == 3
    shard = next((ds / "val").glob("set_*.parquet"))
    keep = shard.read_bytes()
    shard.write_bytes(keep[:-40])
    with pytest.raises(PeelError, match=f"shard {shard} is truncated or corrupt"):
        check_dataset(ds)
    with pytest.raises(PeelError, match="truncated or corrupt"):
        load_split(ds, "val")
    shard.unlink()
    with pytest.raises(PeelError, match="is missing"):
        check_dataset(ds)
    shard.write_bytes(keep)
    shutil.rmtree(ds / "test")
    with pytest.raises(PeelError, match="is missing"):
        check_dataset(ds)
