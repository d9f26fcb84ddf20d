"""``peel record`` as a real process: bad paths and options are one-line errors with exit 2."""

from __future__ import annotations

import subprocess
import sys

import pytest


def _peel(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "peel_bringup.cli", "record", *args],
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("case", ["existing_bag", "file_in_the_way", "parent_is_file"])
def test_unwritable_bag_path_is_one_line_error(tmp_path, case: str) -> None:
    if case == "existing_bag":
        bag = tmp_path / "bag"
        bag.mkdir()
        (bag / "metadata.yaml").write_text("keep me")
    elif case == "file_in_the_way":
        bag = tmp_path / "bag"
        bag.write_text("not a bag")
    else:
        (tmp_path / "plain").write_text("x")
        bag = tmp_path / "plain" / "sub" / "bag"
    out = _peel("--out", str(bag), "--duration", "1")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("peel record: error: cannot write bag ")
    assert str(bag) in lines[0]
    if case == "existing_bag":
        assert (bag / "metadata.yaml").read_text() == "keep me"  # nothing overwritten


def test_unknown_topic_and_bad_duration(tmp_path) -> None:
    out = _peel("--out", str(tmp_path / "b"), "--topics", "/peel/nope")
    assert out.returncode == 2 and "unknown topic '/peel/nope'" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = _peel("--out", str(tmp_path / "b"), "--duration", "-3")
    assert out.returncode == 2 and "--duration" in out.stderr
    assert not (tmp_path / "b").exists()
    out = _peel("--repair", str(tmp_path / "missing"))
    assert out.returncode == 2 and "missing" in out.stderr and "not a directory" in out.stderr


def test_module_entry_points_report_bad_path_in_one_line(tmp_path) -> None:
    """``python -m peel_bag.recorder_cli`` (what peel graph runs) and the ros2-run node (the
    ``peel_recorder`` console script, :func:`peel_bag.recorder_cli.node_main`)."""
    (tmp_path / "f").write_text("x")
    node = "import sys; from peel_bag.recorder_cli import node_main; sys.exit(node_main())"
    for how in (["-m", "peel_bag.recorder_cli"], ["-c", node]):
        out = subprocess.run([sys.executable, *how, "--out", str(tmp_path / "f" / "b"),
                              "--ros-args", "-p", "x:=1"][: 5 if how[0] == "-m" else 8],
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 2, how
        assert out.stderr.strip() == f"peel record: error: cannot write bag {tmp_path}/f/b: " \
                                     "Not a directory"
