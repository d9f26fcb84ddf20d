"""The Nachi bridge's configure step, without ROS: connect to the controller and check its
HELLO (docs/nachi.md, docs/graph.md "Lifecycle").

:func:`connect_checked` tries :meth:`~.link.Connection.open` (TCP + ``HELLO`` + version check)
with the link's :class:`~.link.Backoff` between attempts for at most
``link.configure_timeout_s`` of wall time; the connection it returns is the one the bridge then
serves (:meth:`~.bridge.NachiBridge.start`). No controller within that time is a
:class:`~peel_msgs_py.lifecycle.ConfigureError` naming the address, the attempts and the last
reason (exit status 1 for an autostarted node: the controller, not the input, is at fault).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from peel_msgs_py.lifecycle import ConfigureError

from .config import LinkParams
from .link import Backoff, Connection, LinkError

#: Exit status of an autostarted bridge that found no controller.
NO_CONTROLLER = 1


def connect_checked(link: LinkParams, log: Callable[[str], None],
                    clock: Callable[[], float] = time.monotonic,
                    sleep: Callable[[float], None] = time.sleep) -> Connection:
    """A connection whose HELLO was checked, or :class:`ConfigureError` (module docstring);
    ``log`` gets one line per failed attempt."""
    backoff = Backoff(link.backoff_initial_s, link.backoff_max_s, link.backoff_factor)
    start = clock()
    attempts = 0
    while True:
        attempts += 1
        try:
            return Connection.open(link.host, link.port, link.connect_timeout_s,
                                   link.hello_timeout_s)
        except LinkError as exc:
            why = str(exc)
        waited = clock() - start
        delay = backoff.next()
        if waited + delay > link.configure_timeout_s:
            raise ConfigureError(
                f"giving up: no controller at {link.host}:{link.port} for {waited:.1f} s "
                f"({attempts} attempts; last: {why}; link.configure_timeout_s = "
                f"{link.configure_timeout_s:g} s)", NO_CONTROLLER)
        log(f"{why}; retrying in {delay:.2f} s")
        sleep(delay)
