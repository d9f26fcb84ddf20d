"""Output locations, checked when a command resolves its arguments (before any work starts).

Every command that writes results checks where it will write first, so that a path it cannot
use is a one-line error (:class:`~peel_msgs_py.errors.PeelError`, exit 2) and not a traceback
after minutes of work:

* :func:`check_location`: the path is not under a kernel pseudo file system (``/proc``,
  ``/sys``, ...), its nearest existing ancestor is a directory, and a directory can really be
  created there (a probe ``mkdtemp`` + ``rmdir``: permission bits say nothing for root, and a
  read-only mount only shows when written);
* :func:`check_new_path`: as above, and nothing of that name exists yet (a bag);
* :func:`check_output_files`: file outputs (a checkpoint and the files beside it): the parent
  can be written, no path is a directory, and an existing file is replaced only with ``force``;
* :class:`OutputDir`: a run's output folder (``peel graph``, ``peel experiment``, ``peel
  figures``, ``peel demo``, ``peel soak``). A missing or empty folder is used; a folder holding
  an earlier peel run (the marker file :data:`RUN_MARKER`) is refused, or emptied first with
  ``force``; a non-empty folder that peel did not write is always refused: peel never deletes,
  nor mixes its files with, files it did not write. The folder is created only when the work
  starts (``with out as path:``), and removed again if the work fails before writing anything
  into it, so a refused run never leaves an empty folder behind.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from types import TracebackType

from .atomic import atomic_write_text
from .errors import PeelError

#: Marker file written into every run folder by :class:`OutputDir`.
RUN_MARKER = ".peel_run.json"

#: File systems that are kernel interfaces, not storage.
PSEUDO_FS = frozenset({"proc", "sysfs", "devpts", "cgroup", "cgroup2", "debugfs", "tracefs",
                       "securityfs", "configfs", "bpf", "pstore", "efivarfs", "fusectl",
                       "binfmt_misc", "autofs", "nsfs"})


def _mounts() -> list[tuple[str, str]]:
    """(mount point, file system type) from ``/proc/self/mountinfo``; empty off Linux."""
    try:
        lines = Path("/proc/self/mountinfo").read_text().splitlines()
    except OSError:
        return []
    out = []
    for line in lines:
        left, sep, right = line.partition(" - ")
        fields = left.split()
        if sep and len(fields) >= 5 and right.split():
            point = re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), fields[4])
            out.append((point, right.split()[0]))
    return out


def filesystem_type(path: Path) -> str | None:
    """Type of the file system holding the existing ``path`` (longest mount-point prefix)."""
    p = str(path.resolve())
    best, kind = "", None
    for point, fstype in _mounts():
        inside = p == point or p.startswith(point.rstrip("/") + "/")
        if inside and len(point) >= len(best):
            best, kind = point, fstype
    return kind


def _existing_ancestor(path: Path) -> Path:
    p = Path(os.path.abspath(path))
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_location(path: str | os.PathLike[str], what: str = "--out", *,
                   file: bool = False, probe: bool = True) -> Path:
    """Refuse a path that cannot be created or written (module docstring); returns it.

    ``file=True``: ``path`` is a file to write, so its folder is what must be writable.
    ``probe=False``: only the file system and folder checks, no probe directory.
    """
    path = Path(path)
    base = _existing_ancestor(path.parent if file else path)
    kind = filesystem_type(base)
    if kind in PSEUDO_FS:
        raise PeelError(f"{what} {path}: {base} is on a '{kind}' file system (a kernel "
                        "interface, not storage)")
    if not base.is_dir():
        raise PeelError(f"{what} {path}: {base} is a file, not a folder")
    if not probe:
        return path
    try:
        probe = tempfile.mkdtemp(prefix=".peel-probe-", dir=base)
    except OSError as exc:
        raise PeelError(f"{what} {path}: cannot write in {base}: {exc.strerror}") from None
    os.rmdir(probe)
    return path


def check_new_path(path: str | os.PathLike[str], what: str) -> Path:
    """A path to be created by the command (a bag directory): writable and not there yet."""
    path = Path(path)
    if path.exists() or path.is_symlink():
        kind = "a folder" if path.is_dir() else "a file"
        raise PeelError(f"{what} {path}: {kind} of that name already exists")
    return check_location(path, what)


def check_output_files(paths: list[Path], *, what: str = "--out", force: bool = False) -> None:
    """File outputs: writable parent, none a directory, an existing one only with ``force``."""
    for p in paths:
        if p.is_dir():
            raise PeelError(f"{what} {p} is a folder, not a file")
        check_location(p, what, file=True)
    existing = [p for p in paths if p.exists()]
    if existing and not force:
        raise PeelError(f"{what} {existing[0]} already exists; choose another path or add "
                        "--force to replace it")


class OutputDir:
    """A run's output folder (module docstring); checked on construction, created on entry.

    ::

        out = OutputDir(args.out, command="peel graph", force=args.force)  # checks only
        ...                                    # resolve the other arguments
        with out as run_dir:                   # created (earlier run cleared with force)
            ...                                # the work; a failure before anything is
                                               # written removes the folder again
    """

    def __init__(self, path: str | os.PathLike[str], *, command: str, force: bool = False,
                 what: str = "--out") -> None:
        self.path = Path(path)
        self.command = command
        self.force = force
        self.what = what
        self._created: Path | None = None  # the topmost folder this run created
        self.earlier: dict | None = None
        self.check()

    def check(self) -> None:
        """Refuse a location this run cannot use; nothing is left behind (the writability probe
        runs only in a folder that is new, empty or an earlier peel run)."""
        p = self.path
        if p.exists() and not p.is_dir():
            raise PeelError(f"{self.what} {p} is an existing file, not a folder")
        check_location(p, self.what, probe=False)
        if not p.is_dir() or not any(c.name != RUN_MARKER for c in p.iterdir()):
            check_location(p, self.what)
            return  # new, empty, or left by a run killed before it wrote anything
        self.earlier = read_marker(p)
        if self.earlier is None:
            raise PeelError(f"{self.what} {p} is not empty and holds no peel run; choose a new "
                            "or empty folder (peel never writes among files it did not write)")
        if not self.force:
            when = self.earlier.get("created", "?")
            raise PeelError(f"{self.what} {p} holds an earlier '{self.earlier.get('command')}' "
                            f"run ({when}); choose another folder or add --force to replace it")
        check_location(p, self.what)

    def create(self) -> Path:
        """Create the folder (clearing an earlier run when forced) and write the marker."""
        p = self.path
        if self.earlier is not None and self.force:
            for child in p.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        top = _existing_ancestor(p)
        if not p.exists():  # remember the topmost folder this run creates (absolute)
            self._created = Path(os.path.abspath(p))
            while self._created.parent != top:
                self._created = self._created.parent
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise PeelError(f"{self.what} {p}: cannot create it: {exc.strerror}") from None
        atomic_write_text(p / RUN_MARKER, json.dumps(
            {"command": self.command, "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
             "pid": os.getpid()}) + "\n")
        return p

    def remove_if_unused(self) -> bool:
        """Remove the folder (and the parents this run created) if it holds only the marker."""
        p = self.path
        try:
            if any(c.name != RUN_MARKER for c in p.iterdir()):
                return False
            (p / RUN_MARKER).unlink(missing_ok=True)
            if self._created is None:
                return False  # the folder existed before this run: leave it
            d = Path(os.path.abspath(p))
            while True:
                d.rmdir()
                if d == self._created:
                    break
                d = d.parent
        except OSError:
            return False
        return True

    def __enter__(self) -> Path:
        return self.create()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is not None:
            self.remove_if_unused()


def read_marker(path: Path) -> dict | None:
    """The run marker of folder ``path`` (None when there is none or it is unreadable)."""
    try:
        data = json.loads((path / RUN_MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
