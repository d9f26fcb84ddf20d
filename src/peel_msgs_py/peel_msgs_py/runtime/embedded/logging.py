"""Node loggers with rcutils' console format: ``[INFO] [<unix time>] [<name>]: <message>``.

Output goes to stderr, like rcutils' default console sink. Severity threshold per logger
(``set_level``) or for the process (``--ros-args --log-level LEVEL``); ``once``,
``skip_first`` and ``throttle_duration_sec`` keyword arguments behave as in rclpy.
"""

from __future__ import annotations

import sys
import threading
import time
from enum import IntEnum
from typing import Any

from ...errors import PeelError


class LoggingSeverity(IntEnum):
    """rcutils severities."""

    UNSET = 0
    DEBUG = 10
    INFO = 20
    WARN = 30
    ERROR = 40
    FATAL = 50


_default_level = LoggingSeverity.INFO
_write_lock = threading.Lock()


def parse_level(text: str) -> LoggingSeverity:
    """``info`` / ``WARN`` / ``warning`` ... -> severity; PeelError when unknown."""
    key = text.strip().upper()
    key = {"WARNING": "WARN"}.get(key, key)
    try:
        return LoggingSeverity[key]
    except KeyError:
        raise PeelError(f"unknown log level {text!r}") from None


def set_default_level(level: LoggingSeverity | str) -> None:
    global _default_level
    _default_level = parse_level(level) if isinstance(level, str) else LoggingSeverity(level)


class RcutilsLogger:
    """``node.get_logger()``: ``debug``, ``info``, ``warn``/``warning``, ``error``, ``fatal``."""

    def __init__(self, name: str = "") -> None:
        self.name = name
        self._level = LoggingSeverity.UNSET
        self._seen: dict[tuple[Any, ...], float] = {}

    def get_child(self, name: str) -> RcutilsLogger:
        return RcutilsLogger(f"{self.name}.{name}" if self.name else name)

    def set_level(self, level: LoggingSeverity | int) -> None:
        self._level = LoggingSeverity(level)

    def get_effective_level(self) -> LoggingSeverity:
        return self._level if self._level != LoggingSeverity.UNSET else _default_level

    def is_enabled_for(self, severity: LoggingSeverity) -> bool:
        return severity >= self.get_effective_level()

    def log(self, message: Any, severity: LoggingSeverity, **kwargs: Any) -> bool:
        if not self.is_enabled_for(severity):
            return False
        caller = sys._getframe(2)
        key = (caller.f_code.co_filename, caller.f_lineno)
        now = time.monotonic()
        if kwargs.get("once") and key in self._seen:
            return False
        if kwargs.get("skip_first") and key not in self._seen:
            self._seen[key] = now
            return False
        throttle = kwargs.get("throttle_duration_sec")
        if throttle and key in self._seen and now - self._seen[key] < float(throttle):
            return False
        self._seen[key] = now
        label = severity.name
        line = f"[{label}] [{time.time():.9f}] [{self.name}]: {message}\n"
        with _write_lock:
            sys.stderr.write(line)
            sys.stderr.flush()
        return True

    def debug(self, message: Any, **kwargs: Any) -> bool:
        return self.log(message, LoggingSeverity.DEBUG, **kwargs)

    def info(self, message: Any, **kwargs: Any) -> bool:
        return self.log(message, LoggingSeverity.INFO, **kwargs)

    def warning(self, message: Any, **kwargs: Any) -> bool:
        return self.log(message, LoggingSeverity.WARN, **kwargs)

    warn = warning

    def error(self, message: Any, **kwargs: Any) -> bool:
        return self.log(message, LoggingSeverity.ERROR, **kwargs)

    def fatal(self, message: Any, **kwargs: Any) -> bool:
        return self.log(message, LoggingSeverity.FATAL, **kwargs)


def get_logger(name: str) -> RcutilsLogger:
    """``rclpy.logging.get_logger``."""
    return RcutilsLogger(name)
