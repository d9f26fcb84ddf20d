"""A half-written file never replaces a good one (peel_msgs_py.atomic)."""

import os
from pathlib import Path

import pytest

from peel_msgs_py.atomic import atomic_write, atomic_write_bytes, atomic_write_text


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "model.safetensors"
    atomic_write_bytes(target, b"good weights")

    def half_write(tmp: str) -> None:
        Path(tmp).write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, half_write)
    assert target.read_bytes() == b"good weights"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.safetensors"]


def test_write_creates_parents_keeps_suffix_and_normal_permissions(tmp_path: Path) -> None:
    seen: list[str] = []
    path = atomic_write(tmp_path / "a" / "fig.png", lambda tmp: (seen.append(tmp),
                                                                  Path(tmp).write_bytes(b"png")))
    assert seen[0].endswith(".png") and Path(seen[0]).parent == path.parent
    assert path.read_bytes() == b"png"
    umask = os.umask(0)
    os.umask(umask)
    assert (path.stat().st_mode & 0o777) == (0o666 & ~umask)
    assert atomic_write_text(tmp_path / "r.md", "é").read_text(encoding="utf-8") == "é"
