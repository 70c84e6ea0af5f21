"""Input and output files, checked before a run so that a bad one is refused (exit code 2)
before the drive is touched or any file is created: an input is a regular file of a sane size
(`protocol.input_files`: a device, a FIFO or a huge file is never read), an output is a path
that takes a new file and is none of the command's inputs (also not through a link), and not
a device or a FIFO that writing would replace or block on."""

from __future__ import annotations

import argparse
import os
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path

from protocol.input_files import TEXT_MAX, check_input_file

# (option, path) of each input a command reads, so an output clashing with one is named
Inputs = Iterable[tuple[str, str | None]]


INPUT_OPTIONS = (("--model", "model"), ("--robot", "robot"), ("--eds", "eds"),
                 ("--esi", "esi"), ("--zenoh-config", "zenoh_config"))


def option_inputs(args: argparse.Namespace) -> list[tuple[str, str | None]]:
    """(option, path) of the input files among a command's common options."""
    return [(option, getattr(args, key, None)) for option, key in INPUT_OPTIONS]


def check_input_option(option: str, path: str, what: str, limit: int = TEXT_MAX) -> Path:
    """An input file option: a regular file of at most `limit` bytes, stat'ed without opening
    it (`protocol.input_files`). ValueError names the option and the file."""
    try:
        return check_input_file(path, what, limit)
    except ValueError as exc:
        raise ValueError(f"{option} {exc}") from None


def check_output_file(option: str, path: str, inputs: Inputs = ()) -> Path:
    """A file this command will write: its folder exists and takes a new file, the path is not
    a folder, not a device, FIFO or socket, and not one of `inputs` (same file through a link
    or a hard link included). Probed with a temporary file that is removed at once (permission
    bits say nothing when running as root). ValueError names the option."""
    target = Path(path)
    try:
        if target.is_dir():
            raise ValueError(f"{option} {path}: is a directory; expected a file path")
        folder = target.parent
        if not folder.is_dir():
            raise ValueError(f"{option} {path}: folder {folder} does not exist")
    except OSError as exc:  # too long, a loop of links: the path itself is unusable
        raise ValueError(_unusable(option, path, exc)) from None
    _check_not_an_input(option, path, inputs)
    _probe(option, path, folder)
    return target


def check_output_folder(option: str, path: str) -> Path:
    """A folder this command will create (if needed) and fill: the nearest existing ancestor
    takes new entries. ValueError names the option."""
    target = Path(path)
    try:
        if target.exists() and not target.is_dir():
            raise ValueError(f"{option} {path}: exists and is not a directory")
        existing = target
        while not existing.exists():
            existing = existing.parent
        if not existing.is_dir():
            raise ValueError(f"{option} {path}: {existing} is not a directory")
    except OSError as exc:  # too long, a loop of links: the path itself is unusable
        raise ValueError(_unusable(option, path, exc)) from None
    _probe(option, path, existing)
    return target


def _unusable(option: str, path: str, exc: OSError) -> str:
    return f"{option} {path[:200]}: cannot use this path ({exc.strerror or exc})"


def check_distinct_outputs(outputs: Iterable[tuple[str, str | None]]) -> None:
    """Two output options naming one file would overwrite each other. ValueError names
    both."""
    seen: list[tuple[str, str]] = []
    for option, path in outputs:
        if path is None:
            continue
        for other, earlier in seen:
            if _same_path(path, earlier):
                raise ValueError(f"{option} {path}: the same file as {other} {earlier}; "
                                 "expected a file of its own")
        seen.append((option, path))


def _same_path(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def _check_not_an_input(option: str, path: str, inputs: Inputs) -> None:
    try:
        info = os.stat(path)
    except FileNotFoundError:
        info = None
    except OSError as exc:
        raise ValueError(_unusable(option, path, exc)) from None
    if info is not None and not stat.S_ISREG(info.st_mode):
        raise ValueError(f"{option} {path}: exists and is not a regular file (a device, FIFO "
                         "or socket would be replaced or block); expected a file path")
    for input_option, input_path in inputs:
        if input_path is not None and _same_path(path, input_path):
            raise ValueError(f"{option} {path}: the same file as {input_option} {input_path}; "
                             "expected a new file, not one this command reads")


def _probe(option: str, path: str, folder: Path) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{option} {path}: cannot write in {folder}: "
                         f"{exc.strerror or exc}") from None
