"""cagegen's loggers, and ipctk's C++ log lines routed into them instead of the terminal.

Loggers: ``cagegen`` (with a :class:`logging.NullHandler`: nothing is printed unless the application
configures logging) and its children, among them ``cagegen.ipctk`` for ipctk's own messages.

ipctk logs through spdlog straight to the process's C-level stdout (e.g. "Small gap 1e-16 <= eps in
Additive CCD can lead to missed collisions", met when a cage and the input nearly touch during the
flow: harmless, every cage is certified afterwards) and its Python binding offers no way to give it
another sink, only ``ipctk.set_logger_level``. So:

* outside any ipctk call of cagegen, ipctk's level is ``error`` (:func:`setup_ipctk`, at import of
  :mod:`cagegen.collision`): no warning of an unwrapped call reaches the terminal;
* the calls that can warn (CCD, broad phase, collision sets) run inside :func:`ipctk_to_log`, which
  lowers ipctk's level to ``warn`` and points file descriptor 1 at a temporary file for the duration
  of the call; afterwards each captured line is logged on ``cagegen.ipctk`` at spdlog's level
  (warning -> WARNING, ...). The first message of each kind (numbers aside) is logged at its level,
  repeats at DEBUG, so a long flow does not flood a log. When ``cagegen.ipctk`` does not log
  warnings (``logging.getLogger("cagegen.ipctk").setLevel(logging.ERROR)``) nothing is captured.

While a capture is active anything else written to fd 1 (by another thread) lands in the same
log; the windows are single ipctk calls (milliseconds).
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import logging
import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator

log = logging.getLogger("cagegen")
log.addHandler(logging.NullHandler())  # no "last resort" printing of cagegen's warnings to stderr
ipctk_log = logging.getLogger("cagegen.ipctk")

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_SPDLOG = re.compile(r"^\[[^\]]*\]\s*\[[^\]]*\]\s*\[(\w+)\]\s?(.*)$")  # [time] [ipctk] [warning] text
_LEVELS = {"trace": logging.DEBUG, "debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
           "warn": logging.WARNING, "error": logging.ERROR, "critical": logging.CRITICAL}
_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?")

_lock = threading.Lock()
_state = {"depth": 0, "saved": None, "file": None}
_seen: set[str] = set()


def _ipctk_level(name: str) -> None:
    import ipctk

    ipctk.set_logger_level(getattr(ipctk.LoggerLevel, name))


def setup_ipctk() -> None:
    """ipctk at level ``error`` outside :func:`ipctk_to_log` (called once, at import of the ipctk users)."""
    _ipctk_level("error")


def _flush_c_stdout() -> None:
    """``fflush(NULL)``: C-buffered output goes to the file fd 1 points at now, not after the swap."""
    if "fflush" not in _state:
        try:
            _state["fflush"] = ctypes.CDLL(None).fflush
        except (OSError, AttributeError):  # pragma: no cover - no C library to flush
            _state["fflush"] = None
    if _state["fflush"] is not None:
        _state["fflush"](None)


def _start() -> bool:
    """Point fd 1 at the capture file (first entrant only). False if fd 1 cannot be redirected."""
    if _state["depth"] == 0:
        try:
            if _state["file"] is None:
                _state["file"] = tempfile.TemporaryFile()
                atexit.register(_state["file"].close)
            with contextlib.suppress(Exception):
                sys.stdout.flush()
            _flush_c_stdout()
            saved = os.dup(1)
            os.dup2(_state["file"].fileno(), 1)
        except (OSError, ValueError):
            return False
        _state["saved"] = saved
        _ipctk_level("warn")
    _state["depth"] += 1
    return True


def _stop() -> str:
    """Undo :func:`_start` (last leaver restores fd 1) and return what was captured."""
    _state["depth"] -= 1
    if _state["depth"] > 0:
        return ""
    _ipctk_level("error")
    _flush_c_stdout()
    os.dup2(_state["saved"], 1)
    os.close(_state["saved"])
    fd = _state["file"].fileno()
    size = os.fstat(fd).st_size
    if not size:
        return ""
    text = os.pread(fd, size, 0).decode("utf-8", "replace")
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    return text


def forward_ipctk(text: str) -> None:
    """Log captured spdlog lines on ``cagegen.ipctk``: first of each kind at its level, repeats at DEBUG."""
    for line in _ANSI.sub("", text).splitlines():
        if not line.strip():
            continue
        m = _SPDLOG.match(line)
        level, msg = (_LEVELS.get(m.group(1).lower(), logging.WARNING), m.group(2)) if m else (logging.WARNING, line)
        kind = _NUMBER.sub("#", msg)
        if kind in _seen:
            level = logging.DEBUG
        else:
            _seen.add(kind)
            if level > logging.DEBUG:
                msg += " (repeats of this message are logged at DEBUG)"
        ipctk_log.log(level, "%s", msg)


@contextlib.contextmanager
def ipctk_to_log() -> Iterator[None]:
    """Run the enclosed ipctk calls with their log lines going to ``cagegen.ipctk``, not the terminal."""
    if not ipctk_log.isEnabledFor(logging.WARNING):
        yield
        return
    with _lock:
        active = _start()
    try:
        yield
    finally:
        if active:
            with _lock:
                text = _stop()
            if text:
                forward_ipctk(text)
