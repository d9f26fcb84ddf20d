"""ROS names: validation, expansion (relative, ``~``) and the DDS topic names ROS 2 uses.

DDS names follow ``rmw_cyclonedds_cpp``: topics ``rt<fqn>``, service requests
``rq<fqn>Request``, replies ``rr<fqn>Reply`` (ROS 2 design article "Topic and Service name
mapping to DDS").
"""

from __future__ import annotations

import re

from ...errors import PeelError

_NODE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TOKEN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def validate_node_name(name: str) -> str:
    if not isinstance(name, str) or not _NODE_RE.match(name):
        raise PeelError(f"invalid node name {name!r}: letters, digits and '_', not first a digit")
    return name


def normalize_namespace(ns: str | None) -> str:
    ns = (ns or "").strip()
    if not ns or ns == "/":
        return "/"
    if not ns.startswith("/"):
        ns = "/" + ns
    ns = ns.rstrip("/")
    for tok in ns[1:].split("/"):
        if not _TOKEN_RE.match(tok):
            raise PeelError(f"invalid namespace {ns!r}")
    return ns


def expand_topic_name(name: str, node_name: str, namespace: str) -> str:
    """Fully qualified ROS name of ``name`` for a node (``~`` = the node's own name)."""
    if not isinstance(name, str) or not name:
        raise PeelError(f"invalid topic or service name {name!r}")
    ns = namespace if namespace != "/" else ""
    if name.startswith("~"):
        full = f"{ns}/{node_name}{name[1:]}"
    elif name.startswith("/"):
        full = name
    else:
        full = f"{ns}/{name}"
    if full != "/" and full.endswith("/"):
        raise PeelError(f"invalid topic or service name {name!r}: ends with '/'")
    for tok in full[1:].split("/"):
        if not _TOKEN_RE.match(tok):
            raise PeelError(f"invalid topic or service name {name!r}")
    return full


def dds_topic(fqn: str) -> str:
    return "rt" + fqn


def dds_request(fqn: str) -> str:
    return "rq" + fqn + "Request"


def dds_reply(fqn: str) -> str:
    return "rr" + fqn + "Reply"
