"""Output paths, checked before a run so that a bad one is refused (exit code 2) before the
drive is touched or any file is created."""

from __future__ import annotations

import tempfile
from pathlib import Path


def check_output_file(option: str, path: str) -> Path:
    """A file this command will write: its folder exists and takes a new file, and the path is
    not a folder. Probed with a temporary file that is removed at once (permission bits say
    nothing when running as root). ValueError names the option."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{option} {path}: is a directory; expected a file path")
    folder = target.parent
    if not folder.is_dir():
        raise ValueError(f"{option} {path}: folder {folder} does not exist")
    _probe(option, path, folder)
    return target


def check_output_folder(option: str, path: str) -> Path:
    """A folder this command will create (if needed) and fill: the nearest existing ancestor
    takes new entries. ValueError names the option."""
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise ValueError(f"{option} {path}: exists and is not a directory")
    existing = target
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is not a directory")
    _probe(option, path, existing)
    return target


def _probe(option: str, path: str, folder: Path) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{option} {path}: cannot write in {folder}: "
                         f"{exc.strerror or exc}") from None
