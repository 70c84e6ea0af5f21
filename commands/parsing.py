"""The parser every command uses and the argument types it shares: a bad value is refused
while parsing, naming its option, in one line with exit code 2 (command-line text is parsed in
the commands and nowhere below; the library layers take typed values and raise typed errors)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn


class CommandParser(argparse.ArgumentParser):
    """argparse whose errors are one line, `PROG: error: MESSAGE`, exit code 2 (the usage is
    one `--help` away), and which answers `--version` on every command."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                          help="print the version of actuator-link and exit")

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def doc_description(doc: str) -> str:
    """A command's `--help` description: its module docstring's first paragraph as one
    sentence (the first line alone stopped mid-sentence)."""
    return " ".join(doc.split("\n\n", 1)[0].split())


def package_version() -> str:
    """The installed actuator-link's version (pyproject.toml), or where it runs from when it is
    not installed (a checkout run as `python3 -m commands.X`)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("actuator-link")
    except PackageNotFoundError:
        return "(not installed)"


def usage_error(prog: str, message: str) -> int:
    """Bad usage or input: one line on stderr naming the option or file; exit code 2."""
    print(f"{prog}: error: {message}", file=sys.stderr, flush=True)
    return 2


# --- argument types: a bad value is refused while parsing, naming its option ----------------

def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def finite_float(text: str) -> float:
    value = _number(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return value


def non_negative_float(text: str) -> float:
    value = _number(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number >= 0")
    return value


def positive_float(text: str) -> float:
    value = _number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number > 0")
    return value


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def int_range(low: int, high: int) -> Callable[[str], int]:
    """An argparse type for an integer in [low, high]."""
    def parse(text: str) -> int:
        value = _integer(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{value}: expected {low}..{high}")
        return value

    parse.__name__ = f"integer {low}..{high}"
    return parse


def seed(text: str) -> int:
    """numpy's generators take seeds >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value}: expected an integer >= 0")
    return value


NODE_ID = int_range(1, 127)  # CiA 301 node ids
DEFAULT_NODE_ID = 2  # the elbow drive's
SLAVE_POSITION = int_range(0, 65534)  # 0-based positions on a line (SOEM counts to 65535)
LINE_SLAVES = int_range(1, 64)  # virtual slaves one sim-bus serves on a line (robot files: 64)
TCP_PORT = int_range(1, 65535)
