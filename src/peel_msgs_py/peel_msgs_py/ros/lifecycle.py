"""The managed node the planner and both plant bridges are (``rclpy.lifecycle``; docs/graph.md).

:class:`ManagedNode` maps the standard transitions (:mod:`peel_msgs_py.lifecycle`) onto four
methods a node defines, so that its ``node.py`` stays about what each transition does:

* :meth:`ManagedNode.setup` (configure): check the parameters, build what the node needs;
  raises :class:`~peel_msgs_py.lifecycle.ConfigureError` (or any
  :class:`~peel_msgs_py.errors.PeelError`) with the reason; the node then logs
  ``configure failed: <reason>`` (one line), releases what was half built and stays
  ``unconfigured``;
* :meth:`ManagedNode.start` (activate) and :meth:`ManagedNode.stop` (deactivate);
* :meth:`ManagedNode.release` (cleanup, shutdown, an error, and the node's destruction).

A finalized node (after ``shutdown``) ends its process: with status 0, or, shut down after a
failed configure, with that error's one line and status (:meth:`ManagedNode.exit_error`; how
``peel graph`` ends a node it could not configure).

Lifecycle publishers (``create_lifecycle_publisher``) are enabled on activate and disabled on
deactivate, as rclpy does. With ``node.autostart`` (:data:`~peel_msgs_py.lifecycle.AUTOSTART`)
the node runs configure and activate itself at the end of its construction
(:meth:`ManagedNode.autostart`); a failed configure then raises, so
:func:`~peel_msgs_py.ros.main.run_node` prints the one line and exits with the error's status.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from ..diagnostics import ERROR, OK, Status
from ..errors import PeelError
from ..lifecycle import ACTIVE, FINALIZED, INACTIVE, UNCONFIGURED, ConfigureError

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
E = TypeVar("E", Publisher, Subscription, Timer)


class ManagedNode(LifecycleNode):
    """A lifecycle node whose transitions call :meth:`setup`, :meth:`start`, :meth:`stop` and
    :meth:`release` (module docstring)."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        #: why the last configure failed (None after a successful one)
        self.failure: ConfigureError | None = None
        self.built = False  # setup() succeeded and release() has not run since
        self.quiet = False  # autostart: a failed configure is reported by run_node, not logged
        self.owned: list[Publisher | Subscription | Timer] = []

    # -- what a node defines --------------------------------------------------------------------
    def setup(self) -> None:
        """configure: check the parameters and build the node's parts; raise on a problem."""
        raise NotImplementedError

    def start(self) -> None:
        """activate: let commands flow."""

    def stop(self) -> None:
        """deactivate: stop them (the node stays configured)."""

    def release(self) -> None:
        """cleanup / shutdown: release what :meth:`setup` built besides its :meth:`own`
        entities (also a half-built part)."""

    def own(self, entity: E) -> E:
        """Keep ``entity`` (a publisher, subscription or timer made by :meth:`setup` or
        :meth:`start`) until the release, which destroys it."""
        self.owned.append(entity)
        return entity

    def destroy_owned(self) -> None:
        """Destroy every :meth:`own` entity."""
        while self.owned:
            entity = self.owned.pop()
            if isinstance(entity, LifecyclePublisher):
                self.destroy_lifecycle_publisher(entity)
            elif isinstance(entity, Publisher):
                self.destroy_publisher(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            else:
                self.destroy_timer(entity)

    # -- state ----------------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        """The current state's label (``unconfigured``, ``inactive``, ``active``, ...)."""
        return self._state_machine.current_state[1]

    @property
    def active(self) -> bool:
        return self.lifecycle_state == ACTIVE

    def lifecycle_status(self) -> list[Status]:
        """For ``/diagnostics`` while not active: the state (ERROR with the reason of a failed
        configure); empty while active, when the node's own statuses say everything."""
        state = self.lifecycle_state
        if state == ACTIVE:
            return []
        name = self.get_name()
        if state == UNCONFIGURED and self.failure is not None:
            return [Status(f"{name}: lifecycle", ERROR, f"configure failed: {self.failure}", name,
                           (("state", state),))]
        return [Status(f"{name}: lifecycle", OK, state, name, (("state", state),))]

    # -- rclpy's transition callbacks -----------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self.setup()
        except Exception as exc:  # rclpy would turn anything raised here into ERROR, unsaid
            self.failure = exc if isinstance(exc, ConfigureError) else ConfigureError(
                str(exc) if isinstance(exc, PeelError) else f"{type(exc).__name__}: {exc}",
                2 if isinstance(exc, PeelError) else 1)
            if not self.quiet:
                self.get_logger().error(f"configure failed: {exc}")
            self.release()
            self.destroy_owned()
            return FAILURE
        self.failure, self.built = None, True
        self.get_logger().info("configured (inactive)")
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        super().on_activate(state)  # the lifecycle publishers
        return self.logged("activate", self.start, "activated")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        super().on_deactivate(state)
        return self.logged("deactivate", self.stop, "deactivated")

    def logged(self, what: str, fn: Callable[[], None], done: str) -> TransitionCallbackReturn:
        """Run ``fn``; an exception is logged in one line and raised on (rclpy turns it into
        ERROR: the node releases everything and is unconfigured, :meth:`on_error`)."""
        try:
            fn()
        except Exception as exc:
            self.get_logger().error(f"{what} failed: {type(exc).__name__}: {exc}")
            raise
        self.get_logger().info(done)
        return SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release_all()
        self.get_logger().info("cleaned up (unconfigured)")
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """shutdown: released as by cleanup; the finalized node's process then ends
        (:meth:`exit_error`)."""
        if state.label == ACTIVE:
            self.stop()
        self.release_all()
        self.done = True  # run_node's spin loop ends
        return SUCCESS

    def exit_error(self) -> ConfigureError | None:
        """Once finalized: the failed configure it was shut down after (its process ends with
        that error's line and status), else None."""
        return self.failure if self.lifecycle_state == FINALIZED else None

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().error(f"error while leaving {state.label}; releasing everything")
        self.release_all()
        return SUCCESS  # back to unconfigured

    def release_all(self) -> None:
        """:meth:`release`, once per successful :meth:`setup`."""
        if self.built:
            self.built = False
            self.release()
            self.destroy_owned()

    # -- without a manager ----------------------------------------------------------------------
    def autostart(self, enabled: bool) -> None:
        """With ``enabled`` (``node.autostart``): configure, then activate; a failed configure
        raises its :class:`~peel_msgs_py.lifecycle.ConfigureError`."""
        if not enabled:
            self.get_logger().info(f"{UNCONFIGURED}: waiting for a lifecycle manager "
                                   f"({self.get_fully_qualified_name()}/change_state)")
            return
        self.quiet = True
        try:
            configured = self.trigger_configure() == SUCCESS
        finally:
            self.quiet = False
        if not configured or self.lifecycle_state != INACTIVE:
            raise self.failure or ConfigureError("configure failed")
        self.trigger_activate()

    def destroy_node(self) -> None:
        """Release what is still held (a node stopped by a signal while configured: no
        deactivate runs, the context may be gone), then destroy the node."""
        self.release_all()
        super().destroy_node()
