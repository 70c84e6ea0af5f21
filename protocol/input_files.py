"""Input files checked before they are read: a regular file of a sane size, else one line.

A device node, a FIFO or a multi-gigabyte file given where a small text file is expected must
not be read at all: `/dev/zero` fills memory, `/dev/urandom` never ends, and opening a FIFO
blocks until someone writes to it. `os.stat` answers all of these without opening the file, so
every input is stat'ed first and refused in one line (naming the file and what was expected)
within microseconds. The limits are far above any real file of the kind and far below what a
parser can chew through in a second.
"""

import os
import stat
from pathlib import Path

KIB = 1024
MIB = 1024 * KIB
# the largest accepted file of each kind (real ones: a model or robot file a few KiB, an EDS
# 30-200 KiB, a vendor's ESI with many devices a few MiB, a Zenoh config a few KiB)
TEXT_MAX = 1 * MIB
EDS_MAX = 8 * MIB
ESI_MAX = 32 * MIB
RECORDING_MAX = 16 * 1024 * MIB  # hours of 1 kHz telemetry; garbage is refused by content


class InputFileError(ValueError):
    """An input file that cannot be read as one: the message names the file and what was
    expected, on one line."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def present(path: str | Path) -> bool:
    """Whether anything is at `path`; a path that cannot even be looked up (too long, a loop
    of links, no permission) counts as present, so that `check_input_file` says why in one
    line (`Path.exists` raises for those)."""
    try:
        os.stat(path)
    except FileNotFoundError:
        return False
    except (OSError, ValueError):
        return True
    return True


def check_input_file(path: str | Path, what: str, limit: int) -> Path:
    """`path` is a regular file (links followed) of at most `limit` bytes; `what` names the
    expected content ("an EDS", "a model TOML"). Raises InputFileError in one line."""
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise InputFileError(f"{path}: no such file; expected {what}") from None
    except OSError as exc:  # ENAMETOOLONG, ELOOP, EACCES, ENOTDIR
        raise InputFileError(f"{str(path)[:200]}: cannot read ({exc.strerror or exc}); "
                             f"expected {what}") from None
    except ValueError as exc:  # an embedded NUL byte
        raise InputFileError(f"{str(path)[:200]!r}: {exc}; expected {what}") from None
    if not stat.S_ISREG(info.st_mode):
        raise InputFileError(f"{path}: is {_kind(info.st_mode)}; expected {what} in a "
                             "regular file")
    if info.st_size > limit:
        raise InputFileError(f"{path}: {info.st_size} bytes; expected {what} of at most "
                             f"{limit // MIB} MiB")
    return path


def read_input_file(path: str | Path, what: str, limit: int) -> bytes:
    """The bytes of `path` once `check_input_file` accepts it (at most `limit` read even if
    it grew meanwhile). Raises InputFileError in one line."""
    path = check_input_file(path, what, limit)
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise InputFileError(f"{path}: cannot read ({exc.strerror or exc}); "
                             f"expected {what}") from None
    if len(data) > limit:
        raise InputFileError(f"{path}: over {limit // MIB} MiB; expected {what}")
    return data


def read_input_text(path: str | Path, what: str, limit: int) -> str:
    """`read_input_file` decoded as UTF-8 (a byte-order mark, as Windows editors write, is
    dropped) with CRLF and CR line ends read as LF. Raises InputFileError in one line."""
    data = read_input_file(path, what, limit)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{path}: not UTF-8 text (byte 0x{data[exc.start]:02X} at "
                             f"offset {exc.start}); expected {what}") from None
    return text.replace("\r\n", "\n").replace("\r", "\n")
