"""Dataset generation and loading (sections 3.2, 3.3.1, 4.3).

Layout of a dataset directory::

    DIR/.peel_dataset.json          marker + request (written first; identifies a dataset dir)
    DIR/{train,val,test}/set_KKKKK.parquet   one shard per parameter set P_k (atomic writes)
    DIR/dataset.json                manifest, written last: the dataset is complete

Each shard holds the M trajectories of one parameter set as rows (one per sample) with columns
``traj`` (index in the set), ``k`` (sample index) and the :data:`~peel_msgs_py.trajectory.FIELDS`
in the paper's units; the Parquet key-value metadata ``peel`` holds JSON with the set id, the
seeds, the per-trajectory ``params`` and ``outcome``, the units, the source and the code
version. Sets are split 80/10/10 into train/val/test by a seeded permutation (the paper: 1000
sets x 50 = 40,000/5,000/5,000). Every set's randomness comes from
``SeedSequence(seed, spawn_key=(set,))``, so the bytes do not depend on the worker count, and
finished shards are skipped when a run is resumed.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from peel_msgs_py.atomic import atomic_write_bytes
from peel_msgs_py.errors import PeelError
from peel_msgs_py.trajectory import FIELDS, Trajectory

from .config import SimConfig
from .env import PeelEnv, sample_params
from .episode import run_episode
from .profiles import ExploratoryProfile

SPLITS: tuple[str, ...] = ("train", "val", "test")
MARKER = ".peel_dataset.json"
MANIFEST = "dataset.json"
FORMAT = "peel-dataset/1"
UNITS = {"t": "s", "q": "mm", "v": "mm/s", "u": "mm/s", "fx": "N", "fz": "N", "psi": "mm"}


def code_version() -> str:
    """Package version plus a hash of this package's source files."""
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for p in sorted(here.glob("*.py")):
        if p.name == "node.py":
            continue
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return f"peel_sim_node-0.1.0+src.{h.hexdigest()[:12]}"


def config_hash(cfg: SimConfig, source: str | None = None) -> str:
    """Hash of the simulator parameters that shape the data of ``source``: every group but
    ``dataset.*`` and ``sequence.*`` (experiments only); for ``source="sim"`` also not the plant
    levels' groups (``plant.*``, ``plant_l2.*``, ``plant_l3.*``), which cannot change simulator
    data (so tuning the plant does not invalidate simulator datasets). The bridge's slowdown
    zone (``safety.slowdown.*``, Eq. M6) counts only when it is enabled: off, it leaves every
    command as sent, whatever its other settings."""
    skip = (("dataset.", "sequence.", "plant.", "plant_l2.", "plant_l3.") if source == "sim"
            else ("dataset.", "sequence."))
    if not cfg.flat.get("safety.slowdown.enabled", False):
        skip += ("safety.slowdown.",)
    flat = {k: v for k, v in cfg.flat.items() if not k.startswith(skip)}
    return hashlib.sha256(json.dumps(flat, sort_keys=True).encode()).hexdigest()[:16]


def split_of_sets(n_sets: int, seed: int) -> list[str]:
    """80/10/10 split by parameter set (seeded permutation); at least one val and one test set
    when there are 3 or more sets."""
    n_val = round(0.1 * n_sets)
    n_test = round(0.1 * n_sets)
    if n_sets >= 3:
        n_val, n_test = max(n_val, 1), max(n_test, 1)
    perm = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**31,))).permutation(
        n_sets)
    out = ["train"] * n_sets
    for i in perm[:n_val]:
        out[i] = "val"
    for i in perm[n_val:n_val + n_test]:
        out[i] = "test"
    return out


@dataclass(frozen=True)
class Request:
    """What a dataset directory holds (compared when resuming)."""

    param_sets: int
    per_set: int
    seed: int
    source: str
    config_hash: str

    def as_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "param_sets": self.param_sets, "per_set": self.per_set,
                "seed": self.seed, "source": self.source, "config_hash": self.config_hash}


def _shard_path(out: Path, split: str, set_id: int) -> Path:
    return out / split / f"set_{set_id:05d}.parquet"


def generate_set(cfg: SimConfig, set_id: int, per_set: int, seed: int, source: str,
                 ) -> list[Trajectory]:
    """The M trajectories of parameter set ``set_id`` (deterministic in seed and set_id)."""
    ss = np.random.SeedSequence(seed, spawn_key=(set_id,))
    p_seed, *t_seeds = ss.spawn(per_set + 1)
    params = sample_params(cfg, np.random.default_rng(p_seed), source)
    n_ctrl = int(np.ceil(cfg.task.t_max_s / cfg.task.control_period_s)) + 1
    trajs = []
    env = PeelEnv(cfg, source=source, seed=0, params=params)
    try:
        for j, ts in enumerate(t_seeds):
            prof_seed, env_seed = ts.spawn(2)
            prof = ExploratoryProfile(np.random.default_rng(prof_seed), cfg.dataset.u_min_mmps,
                                      cfg.dataset.u_max_mmps, n_ctrl, cfg.samples_per_control)
            env_int = int(np.random.default_rng(env_seed).integers(0, 2**63 - 1))
            tr = run_episode(env, prof, seed=env_int, params=params)
            tr.meta = {"source": source, "set": set_id, "traj": j, "seed": seed,
                       "env_seed": env_int, "dt_s": cfg.task.dt_s}
            trajs.append(tr)
    finally:
        env.close()
    return trajs


def shard_bytes(trajs: list[Trajectory], set_id: int, req: Request) -> bytes:
    """Serialise one parameter set's trajectories to Parquet bytes (deterministic)."""
    cols: dict[str, list[np.ndarray]] = {"traj": [], "k": []}
    for name in FIELDS:
        cols[name] = []
    info = []
    for j, tr in enumerate(trajs):
        n = len(tr)
        cols["traj"].append(np.full(n, j, dtype=np.int32))
        cols["k"].append(np.arange(n, dtype=np.int32))
        for name in FIELDS:
            cols[name].append(getattr(tr, name))
        info.append({"traj": j, "outcome": tr.outcome, "params": tr.params, "meta": tr.meta,
                     "n": n})
    table = pa.table({k: pa.array(np.concatenate(v)) for k, v in cols.items()})
    meta = {"format": FORMAT, "set": set_id, **req.as_dict(), "units": UNITS,
            "code_version": code_version(), "trajectories": info}
    table = table.replace_schema_metadata({"peel": json.dumps(meta, sort_keys=True)})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def _shard_valid(path: Path, set_id: int, req: Request) -> bool:
    try:
        md = pq.read_schema(path).metadata or {}
        meta = json.loads(md[b"peel"])
    except Exception:
        return False
    return (meta.get("set") == set_id and meta.get("config_hash") == req.config_hash
            and meta.get("seed") == req.seed and meta.get("source") == req.source
            and meta.get("per_set") == req.per_set and len(meta.get("trajectories", [])) == req.per_set)


def _work(args: tuple[SimConfig, int, Request, str]) -> tuple[int, str, int]:
    cfg, set_id, req, out = args
    trajs = generate_set(cfg, set_id, req.per_set, req.seed, req.source)
    split = split_of_sets(req.param_sets, req.seed)[set_id]
    path = _shard_path(Path(out), split, set_id)
    atomic_write_bytes(path, shard_bytes(trajs, set_id, req))
    return set_id, split, sum(len(t) for t in trajs)


def prepare_dir(out: Path, req: Request) -> None:
    """Create or check the output directory: refuses a non-empty directory that is not a
    dataset, or a dataset made with other settings."""
    if out.exists() and not out.is_dir():
        raise PeelError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        marker = out / MARKER
        if not marker.is_file():
            raise PeelError(f"--out {out} exists and is not a peel dataset directory (no {MARKER})")
        try:
            old = json.loads(marker.read_text())
        except (OSError, ValueError):
            raise PeelError(f"--out {out}: unreadable {MARKER}") from None
        if old != req.as_dict():
            diff = sorted(k for k in req.as_dict() if old.get(k) != req.as_dict()[k])
            raise PeelError(f"--out {out} holds a dataset made with other settings "
                            f"(differs in: {', '.join(diff)})")
    out.mkdir(parents=True, exist_ok=True)
    for s in SPLITS:
        (out / s).mkdir(exist_ok=True)
    atomic_write_bytes(out / MARKER, json.dumps(req.as_dict(), sort_keys=True).encode())


def generate_dataset(cfg: SimConfig, out: str | os.PathLike[str], *, param_sets: int,
                     per_set: int, seed: int = 0, source: str = "sim", workers: int = 1,
                     progress: bool = True) -> dict[str, Any]:
    """Generate (or resume) a dataset; returns the manifest."""
    from tqdm import tqdm

    if param_sets < 1:
        raise PeelError(f"--param-sets must be >= 1, got {param_sets}")
    if per_set < 1:
        raise PeelError(f"--per-set must be >= 1, got {per_set}")
    if workers < 1:
        raise PeelError(f"--workers must be >= 1, got {workers}")
    if seed < 0:
        raise PeelError(f"--seed must be >= 0, got {seed}")
    if source not in ("sim", "plant"):
        raise PeelError(f"--source must be sim or plant, got {source!r}")
    out = Path(out)
    req = Request(param_sets, per_set, seed, source, config_hash(cfg, source))
    prepare_dir(out, req)
    (out / MANIFEST).unlink(missing_ok=True)
    splits = split_of_sets(param_sets, seed)
    todo = [k for k in range(param_sets)
            if not _shard_valid(_shard_path(out, splits[k], k), k, req)]
    jobs = [(cfg, k, req, str(out)) for k in todo]
    bar = tqdm(total=param_sets, initial=param_sets - len(todo), unit="set", desc="peel dataset",
               disable=not progress)
    try:
        if workers == 1 or len(jobs) <= 1:
            for j in jobs:
                _work(j)
                bar.update(1)
        else:
            with get_context("fork").Pool(min(workers, len(jobs))) as pool:
                for _ in pool.imap_unordered(_work, jobs):
                    bar.update(1)
    finally:
        bar.close()
    counts = {s: 0 for s in SPLITS}
    for s in splits:
        counts[s] += 1
    manifest = {**req.as_dict(), "splits": {s: {"sets": counts[s],
                                                "trajectories": counts[s] * per_set}
                                            for s in SPLITS},
                "set_split": splits, "units": UNITS, "code_version": code_version(),
                "fields": list(FIELDS)}
    atomic_write_bytes(out / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True).encode())
    return manifest


def _shard_error(path: Path, exc: Exception) -> PeelError:
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return PeelError(f"dataset shard {path} is truncated or corrupt ({detail}); run "
                     "'peel dataset' on the same --out again to regenerate it")


def read_shard(path: str | os.PathLike[str]) -> list[Trajectory]:
    """The trajectories of one shard; PeelError naming the shard when it cannot be read."""
    path = Path(path)
    try:
        table = pq.read_table(path)
        meta = json.loads(table.schema.metadata[b"peel"])
        traj = table.column("traj").to_numpy()
        arr = np.stack([table.column(n).to_numpy() for n in FIELDS], axis=1).astype(np.float64)
        infos = [(i["traj"], i["outcome"], i["params"], i["meta"]) for i in meta["trajectories"]]
    except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as exc:
        raise _shard_error(path, exc) from None
    out = []
    for j, outcome, params, tmeta in infos:
        rows = arr[traj == j]
        out.append(Trajectory.from_array(rows, outcome=outcome, params=params, meta=tmeta))
    return out


def check_dataset(dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Check a dataset before it is used (``peel train``, ``peel figures``); returns its manifest.

    The manifest must be readable and every shard it lists present, with a Parquet footer and
    our metadata for its set. This reads footers only (a shard cut short has no footer), so a
    damaged dataset is refused in a moment instead of after minutes of loading or training.
    """
    d = Path(dir)
    if not d.is_dir():
        raise PeelError(f"dataset {d} is not a directory")
    try:
        man = json.loads((d / MANIFEST).read_text())
        splits = list(man["set_split"])
    except FileNotFoundError:
        raise PeelError(f"{d} is not a complete peel dataset (no {MANIFEST})") from None
    except (OSError, ValueError, KeyError, TypeError):
        raise PeelError(f"dataset {d}: {MANIFEST} is unreadable or not a peel manifest") from None
    for set_id, split in enumerate(splits):
        path = _shard_path(d, split, set_id)
        if not path.is_file():
            raise PeelError(f"dataset {d}: shard {path.relative_to(d)} is missing; run "
                            "'peel dataset' on the same --out again to regenerate it")
        try:
            meta = json.loads((pq.read_schema(path).metadata or {})[b"peel"])
        except (OSError, ValueError, KeyError, TypeError, pa.ArrowException) as exc:
            raise _shard_error(path, exc) from None
        if meta.get("set") != set_id:
            raise PeelError(f"dataset shard {path} holds set {meta.get('set')}, not {set_id}")
    return man


def load_split(dir: str | os.PathLike[str], split: str) -> list[Trajectory]:
    """All trajectories of ``split`` (train / val / test) of a complete dataset, ordered by set
    and trajectory index."""
    if split not in SPLITS:
        raise PeelError(f"split must be one of {SPLITS}, got {split!r}")
    d = Path(dir)
    if not (d / MANIFEST).is_file():
        raise PeelError(f"{d} is not a complete peel dataset (no {MANIFEST})")
    out: list[Trajectory] = []
    for p in sorted((d / split).glob("set_*.parquet")):
        out.extend(read_shard(p))
    return out


def iter_all(dir: str | os.PathLike[str]) -> Iterable[Trajectory]:
    """Every trajectory of a dataset, split by split."""
    for s in SPLITS:
        yield from load_split(dir, s)
