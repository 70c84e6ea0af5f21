"""`--log-level` and the process's logging: one `PROG: LEVEL: message` line on stderr per
warning or error, each read once; `job_error` reports a failed job (exit code 1)."""

from __future__ import annotations

import argparse
import functools
import logging
import signal
import sys
import threading
from collections.abc import Callable

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


def internal_error(exc: BaseException) -> str:
    """An unexpected exception as one line for the user (its traceback goes to the debug log,
    shown with --log-level debug)."""
    logging.getLogger("commands").debug("unexpected exception", exc_info=exc)
    text = " ".join(str(exc).split())[:300]
    return f"internal error: {type(exc).__name__}" + (f": {text}" if text else "")


class ThreadFailures:
    """While installed, an exception that ends any thread (python-can's receive thread, the
    telemetry publisher, a bus's watchdog) is recorded and `on_failure` is called once, so the
    command ends the run (quick stop, close, exit 1) instead of printing a traceback and
    hanging on the threads left behind. A context manager: the previous hook comes back."""

    def __init__(self, on_failure: Callable[[], None]) -> None:
        self._on_failure = on_failure
        self._lock = threading.Lock()
        self.first: str | None = None  # "thread NAME: internal error: ..." of the first one
        self._previous = threading.excepthook

    def _hook(self, args: threading.ExceptHookArgs) -> None:
        if args.exc_type is SystemExit:
            return
        with self._lock:
            if self.first is not None:
                return
            name = args.thread.name if args.thread is not None else "?"
            self.first = f"thread {name}: {internal_error(args.exc_value)}"
        self._on_failure()

    def __enter__(self) -> ThreadFailures:
        self._previous = threading.excepthook
        threading.excepthook = self._hook
        return self

    def __exit__(self, *exc_info) -> None:
        threading.excepthook = self._previous


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def reports_failures(prog: str) -> Callable[[Callable[..., int]], Callable[..., int]]:
    """The last net of a command's `main`: an exception nothing else caught (a bug, or an
    input no check foresaw) is one line, `PROG: error: internal error: TYPE: message`, and
    exit code 1, never a traceback (it goes to --log-level debug). Usage errors and signals
    pass through (SystemExit, KeyboardInterrupt are not Exceptions). The SIGINT and SIGTERM
    handlers a `main` sets (to end its run) are given back when it returns: a program that
    calls it (tests/gap_case.py records, then identifies, in one process) otherwise went on
    with a handler that set a stale stop event, and ignored SIGTERM."""
    def wrap(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def run(argv: list[str] | None = None) -> int:
            previous = [(signum, signal.getsignal(signum)) for signum in _STOP_SIGNALS]
            try:
                return main(argv)
            except Exception as exc:
                print(f"{prog}: error: {internal_error(exc)}", file=sys.stderr, flush=True)
                return 1
            finally:
                if threading.current_thread() is threading.main_thread():
                    for signum, handler in previous:
                        if handler is not None:  # None: set outside Python, left as it is
                            signal.signal(signum, handler)
        return run
    return wrap
