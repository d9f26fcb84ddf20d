"""A learner that stops and comes back (model_learner_node.resume): it goes on from the state it
wrote after its last task, so its next update is the very one it would have made without the
stop (the same checkpoint bytes); a state that does not fit its weights, or a file that is not a
state, is refused with the file named; a file in out_dir is never overwritten."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from peel_model.checkpoint import read_checkpoint_config
from peel_msgs_py.errors import PeelError

PRODUCER = "/model_learner_node"


class _Log:
    def info(self, msg: str) -> None:
        pass

    warn = error = info


def _values(out: Path, **over: Any) -> dict[str, Any]:
    from model_learner_node.parameters import SPECS
    from peel_msgs_py.params import load_node_params, validate

    known = {s.name for s in SPECS}
    flat = {k: v for k, v in load_node_params("model_learner_node").items() if k in known}
    # several meta steps per update, so that the meta-optimiser's moments carry over
    flat.update({"node.out_dir": str(out), "maml.meta_steps": 3, "maml.support_slices": 4,
                 "maml.query_slices": 4, "maml.eval_slices": 4, "maml.m": 2})
    flat.update(over)
    return validate(SPECS, flat)


@pytest.fixture(scope="module")
def peels() -> list[Any]:
    """Three finished plant tasks of different speeds, task_index 0-2."""
    from peel_sim_node.config import load_sim_config
    from peel_sim_node.env import PeelEnv
    from peel_sim_node.episode import run_episode

    env = PeelEnv(load_sim_config(), source="plant", seed=4)
    try:
        out = []
        for k, speed in enumerate((3.0, 5.0, 4.0)):
            traj = run_episode(env, lambda _h, s=speed: s, seed=10 + k)
            traj.meta["task_index"] = k
            out.append(traj)
    finally:
        env.close()
    return out


def _sha(path: Path) -> str:
    return str(read_checkpoint_config(path)["safetensors_sha256"])


def test_a_resumed_learner_makes_the_update_it_would_have_made(tmp_path: Path,
                                                               peels: list[Any]) -> None:
    from model_learner_node.online import OnlineLearner

    straight = OnlineLearner(_values(tmp_path / "straight"), producer=PRODUCER)
    reports = [straight.learn(p, _Log()) for p in peels]
    assert [r.status for r in reports] == ["offered"] * 3

    first = OnlineLearner(_values(tmp_path / "stopped"), producer=PRODUCER)
    for p in peels[:2]:
        first.learn(p, _Log())
    del first  # the learner stops after task 2; its state is on disk
    again = OnlineLearner(_values(tmp_path / "stopped"), producer=PRODUCER)
    assert again.resumed is not None and len(again.pool) == 2 and again.n_tasks == 2
    assert again.init_path.name == "model_v0002.safetensors"
    assert "resumed from learner_state.safetensors" in again.describe()
    # the bridge's history brings task 1 again: learned already; task 3 is new
    assert again.has_learned(peels[0]) and not again.has_learned(peels[2])
    report = again.learn(peels[2], _Log())
    assert Path(report.path).name == "model_v0003.safetensors"
    assert report.sha256 == reports[2].sha256  # the same bytes as without the stop


def test_without_resume_it_starts_afresh_and_overwrites_nothing(tmp_path: Path,
                                                                peels: list[Any]) -> None:
    from model_learner_node.online import OnlineLearner

    out = tmp_path / "models"
    first = OnlineLearner(_values(out), producer=PRODUCER)
    for p in peels[:2]:
        first.learn(p, _Log())
    kept = {p.name: _sha(p) for p in out.glob("model_v*.safetensors")}
    fresh = OnlineLearner(_values(out, **{"node.resume": False}), producer=PRODUCER)
    assert fresh.resumed is None and len(fresh.pool) == 0
    report = fresh.learn(peels[0], _Log())
    assert Path(report.path).name == "model_v0003.safetensors"  # after the files there
    assert {name: _sha(out / name) for name in kept} == kept
    # from the shipped model again: the very update of the first learner's task 1, in a file
    # of its own
    assert report.sha256 == kept["model_v0001.safetensors"]


def test_a_state_that_does_not_fit_its_weights_is_refused(tmp_path: Path,
                                                          peels: list[Any]) -> None:
    import json

    from model_learner_node.online import OnlineLearner
    from model_learner_node.resume import LearnerStateError

    out = tmp_path / "models"
    OnlineLearner(_values(out), producer=PRODUCER).learn(peels[0], _Log())
    config = out / "model_v0001.json"
    cfg = json.loads(config.read_text())
    cfg["safetensors_sha256"] = "0" * 64  # weights of another moment than the state's
    config.write_text(json.dumps(cfg))
    with pytest.raises(LearnerStateError, match=r"learner_state\.safetensors: its weights "
                                                r"model_v0001\.safetensors have SHA-256 000000"):
        OnlineLearner(_values(out), producer=PRODUCER)
    (out / "model_v0001.json").unlink()
    with pytest.raises(LearnerStateError, match=r"its weights model_v0001\.safetensors: cannot "
                                                r"read checkpoint config"):
        OnlineLearner(_values(out), producer=PRODUCER)


@pytest.mark.parametrize("content", [b"", b"not a safetensors file at all", b"\x08" + b"\0" * 7])
def test_a_file_that_is_not_a_state_is_refused(tmp_path: Path, content: bytes) -> None:
    from model_learner_node.online import OnlineLearner
    from model_learner_node.resume import STATE_FILE, LearnerStateError

    out = tmp_path / "models"
    out.mkdir()
    (out / STATE_FILE).write_bytes(content)
    with pytest.raises(LearnerStateError, match=r"learner_state\.safetensors: not a readable"):
        OnlineLearner(_values(out), producer=PRODUCER)
    assert issubclass(LearnerStateError, PeelError)  # a one-line error and exit 2 in the node


def test_a_state_of_another_format_is_refused(tmp_path: Path) -> None:
    import numpy as np
    from safetensors.numpy import save_file

    from model_learner_node.online import OnlineLearner
    from model_learner_node.resume import STATE_FILE, LearnerStateError

    out = tmp_path / "models"
    out.mkdir()
    save_file({"x": np.zeros(2)}, str(out / STATE_FILE), metadata={"format": "other/9"})
    with pytest.raises(LearnerStateError, match=r"format 'other/9', expected "
                                                r"'peel.learner_state/1'"):
        OnlineLearner(_values(out), producer=PRODUCER)
