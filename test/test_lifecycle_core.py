"""The ROS-free parts of the lifecycle (docs/graph.md "Lifecycle"): the Nachi bridge's configure
step (:func:`peel_nachi_bridge.connect.connect_checked`) and the manager's waves of transitions
(:class:`peel_bringup.lifecycle_node.Sequence`) against a stand-in of the services."""

from __future__ import annotations

import socket
from dataclasses import replace

import pytest

from peel_bringup.lifecycle_node import PROBE_S, Sequence, bring_up, transitions
from peel_msgs_py.errors import PeelError
from peel_msgs_py.lifecycle import ConfigureError, goal_state
from peel_nachi_bridge.config import load_config
from peel_nachi_bridge.connect import NO_CONTROLLER, connect_checked
from peel_nachi_emulator.emulator import ControllerEmulator, EmulatorOptions


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.t += dt


def test_no_controller_fails_configure_after_the_backoff_within_the_timeout() -> None:
    port = _free_port()  # nothing listens there
    link = replace(load_config().link, port=port, backoff_initial_s=0.2, backoff_factor=2.0,
                   backoff_max_s=5.0, configure_timeout_s=1.0)
    clock, lines = FakeClock(), []
    with pytest.raises(ConfigureError) as err:
        connect_checked(link, lines.append, clock=clock, sleep=clock.sleep)
    # attempts at 0, 0.2 and 0.6 s; the next (after 0.8 s more) would be past 1.0 s
    assert err.value.exit_status == NO_CONTROLLER
    assert f"giving up: no controller at 127.0.0.1:{port} for 0.6 s (3 attempts; last: " \
           f"cannot connect to 127.0.0.1:{port}" in str(err.value)
    assert [ln.rsplit(";", 1)[1] for ln in lines] == [" retrying in 0.20 s", " retrying in 0.40 s"]


def test_a_listening_controller_is_connected_and_its_hello_checked() -> None:
    emu = ControllerEmulator(EmulatorOptions(port=0, seed=3, source="sim"),
                             log=lambda text: None).start()
    try:
        link = replace(load_config().link, port=emu.port)
        conn = connect_checked(link, lambda line: pytest.fail(line))
        try:
            assert conn.hello.controller_id and conn.peer == f"127.0.0.1:{emu.port}"
        finally:
            conn.close()
    finally:
        emu.close()


class Done:
    """A future with ``success`` (and ``current_state.label``); ``lost``: never answered."""

    def __init__(self, success: bool, label: str = "", lost: bool = False) -> None:
        state = type("S", (), {"label": label})()
        self._result = type("R", (), {"success": success, "current_state": state})()
        self.lost = lost

    def done(self) -> bool:
        return not self.lost

    def result(self) -> object:
        return self._result


class FakeLifecycle:
    """Stands in for :class:`~peel_bringup.lifecycle_node.Lifecycle`: records the requests and
    keeps each node's state; ``refuse`` names (node, transition) answered with failure,
    ``absent`` nodes never appear; ``lose_answer``: the transition runs, its answer is lost
    (the first time); ``lose_request``: the first request never arrives."""

    def __init__(self, refuse: tuple[tuple[str, str], ...] = (), absent: tuple[str, ...] = (),
                 lose_answer: tuple[tuple[str, str], ...] = (),
                 lose_request: tuple[tuple[str, str], ...] = ()) -> None:
        self.asked: list[tuple[str, str]] = []
        self.probes: list[str] = []
        self.refuse, self.absent = refuse, absent
        self.lose_answer, self.lose_request = set(lose_answer), set(lose_request)
        self.states: dict[str, str] = {}

    def ready(self, target: str) -> bool:
        return target not in self.absent

    def change(self, target: str, transition: str) -> Done:
        goal = goal_state(transition)
        key = (target, transition)
        self.asked.append(key)
        if key in self.lose_request:
            self.lose_request.discard(key)
            return Done(False, lost=True)
        ok = key not in self.refuse
        if ok:
            self.states[target] = goal
        lost = key in self.lose_answer
        self.lose_answer.discard(key)
        return Done(ok, lost=lost)

    def state(self, target: str) -> Done:
        self.probes.append(target)
        return Done(False, self.states.get(target, "unconfigured"))


def _run(seq: Sequence, until: float = 10.0) -> None:
    t = 0.0
    while not seq.done and t < until:
        seq.step(t)
        t += 0.5


def test_bring_up_configures_all_at_once_then_activates_in_order() -> None:
    lc = FakeLifecycle()
    seq = bring_up(lc, ["peel_planner_node", "peel_sim_node"], timeout_s=5.0)  # type: ignore[arg-type]
    seq.step(0.0)
    assert lc.asked == [("peel_planner_node", "configure"), ("peel_sim_node", "configure")]
    _run(seq)
    assert seq.done and seq.error is None
    assert lc.asked[2:] == [("peel_planner_node", "activate"), ("peel_sim_node", "activate")]


def test_a_refused_configure_ends_the_bring_up_naming_the_node() -> None:
    lc = FakeLifecycle(refuse=(("peel_sim_node", "configure"),))
    seq = bring_up(lc, ["peel_planner_node", "peel_sim_node"], timeout_s=5.0)  # type: ignore[arg-type]
    _run(seq)
    assert seq.failed == ["peel_sim_node"] and seq.late == []
    assert seq.error == "peel_sim_node: configure failed (it stays unconfigured; its log says why)"
    assert ("peel_planner_node", "activate") not in lc.asked  # nothing activated


def test_a_node_that_never_appears_is_late_after_the_timeout() -> None:
    lc = FakeLifecycle(absent=("peel_nachi_bridge",))
    seq = transitions(lc, "configure", ["peel_nachi_bridge"], timeout_s=2.0)  # type: ignore[arg-type]
    seq.step(0.0)
    seq.step(1.5)
    assert not seq.done
    seq.step(2.5)
    assert seq.late == ["peel_nachi_bridge"] and seq.failed == []
    assert seq.error == ("peel_nachi_bridge: no /peel_nachi_bridge/change_state service within "
                         "2 s")


def test_a_lost_answer_is_taken_from_get_state_and_not_sent_again() -> None:
    lc = FakeLifecycle(lose_answer=(("peel_planner_node", "configure"),))
    seq = bring_up(lc, ["peel_planner_node"], timeout_s=60.0)  # type: ignore[arg-type]
    seq.step(0.0)
    seq.step(PROBE_S - 0.5)
    assert lc.probes == [] and not seq.done  # no get_state before PROBE_S
    _run(seq, until=60.0)
    assert seq.done and seq.error is None, seq.error
    assert lc.asked == [("peel_planner_node", "configure"), ("peel_planner_node", "activate")]
    assert lc.probes == ["peel_planner_node"]


def test_a_lost_request_is_sent_again_once_get_state_shows_it_never_ran() -> None:
    lc = FakeLifecycle(lose_request=(("peel_sim_node", "activate"),))
    lc.states["peel_sim_node"] = "inactive"
    seq = transitions(lc, "activate", ["peel_sim_node"], timeout_s=60.0)  # type: ignore[arg-type]
    _run(seq, until=60.0)
    assert seq.done and seq.error is None, seq.error
    assert lc.asked == [("peel_sim_node", "activate")] * 2 and lc.states["peel_sim_node"] == "active"


def test_a_refusal_whose_answer_was_lost_ends_the_wave_at_the_next_refusal() -> None:
    lc = FakeLifecycle(refuse=(("peel_sim_node", "configure"),),
                       lose_answer=(("peel_sim_node", "configure"),))
    seq = transitions(lc, "configure", ["peel_sim_node"], timeout_s=20.0)  # type: ignore[arg-type]
    _run(seq, until=30.0)
    # the refusal's answer was lost, get_state says unconfigured: sent again, and its second
    # answer (a refusal) ends the wave
    assert seq.failed == ["peel_sim_node"] and len(lc.asked) == 2


def test_an_unknown_transition_is_refused_in_one_line() -> None:
    with pytest.raises(PeelError, match="unknown lifecycle transition 'start'; one of configure"):
        goal_state("start")
