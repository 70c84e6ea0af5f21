"""`--log-level` and the process's logging: one `PROG: LEVEL: message` line on stderr per
warning or error, each read once; `job_error` reports a failed job (exit code 1)."""

from __future__ import annotations

import argparse
import logging
import sys
import threading

LOG_LEVELS = ("debug", "info", "warning", "error")


def add_logging_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-level", choices=LOG_LEVELS, default="warning",
                        help="what the libraries report on stderr (default: %(default)s); "
                             "errors always show")


class _Once(logging.Filter):
    """Passes each warning or error text once: a fault that a library logs and the command then
    reports (as is, or behind its own words: "drive failed: <the fault>") is read once, and a
    warning repeated every cycle does not flood the terminal."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        text = record.getMessage()
        with self._lock:
            if text in self._seen or any(text.endswith(": " + seen) for seen in self._seen):
                return False
            self._seen.add(text)
        return True


def configure_logging(prog: str, level: str) -> None:
    """Logging for the whole process, once: `PROG: LEVEL: message` on stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"{prog}: %(levelname)s: %(message)s"))
    handler.addFilter(_Once())
    logging.addLevelName(logging.DEBUG, "debug")
    logging.addLevelName(logging.INFO, "info")
    logging.addLevelName(logging.WARNING, "warning")
    logging.addLevelName(logging.ERROR, "error")
    logging.addLevelName(logging.CRITICAL, "critical")
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)


def job_error(prog: str, message: str) -> int:
    """The job failed (exit code 1): the reason goes through logging, so a fault the library
    already logged is read once."""
    logging.getLogger(prog).error("%s", message)
    return 1
