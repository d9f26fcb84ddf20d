"""The one exception type that command-line entry points turn into a one-line error.

Library code raises :class:`PeelError` (or a subclass) for bad input: a wrong-typed parameter, an
unreadable file, an unknown message type. ``peel`` and every node's ``main`` catch it, print
``<prog>: error: <message>`` on stderr and exit with status 2, without a traceback.
"""

from __future__ import annotations


class PeelError(Exception):
    """Bad input or an unrecoverable condition; the message names what is wrong."""


class ParameterError(PeelError):
    """A parameter is missing, has the wrong type, or lies outside its documented range."""


class CheckpointError(PeelError):
    """A checkpoint file is truncated, mismatched, or not a safetensors checkpoint of ours."""


class DomainTaken(PeelError):
    """Another peel graph runs on the ROS domain; nothing was started (``peel graph`` exit 5)."""

    exit_status = 5
