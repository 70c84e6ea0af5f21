"""CSV recordings as in DESIGN.md's contract: UTF-8 text (a byte-order mark, as spreadsheets
write, is allowed), a header `t,q,current,joint_torque` (s, rad, A, N.m) after optional
`# key=value` metadata lines, one row per sample."""

import csv
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from model.model_file import write_atomically
from recorder.recording import Recording, RecordingError

COLUMNS = ("t", "q", "current", "joint_torque")
MAX_LINE = 1024 * 1024  # characters: a row is some 50; extra columns are allowed


def read_csv(path: Path) -> Recording:
    try:
        return _read_csv(path)
    except UnicodeDecodeError as exc:
        raise RecordingError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02X}); "
                             f"expected a CSV recording with the header {','.join(COLUMNS)} or "
                             "an MCAP file") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror}") from None
    except csv.Error as exc:  # a field over the csv module's limit (128 KiB), a NUL byte
        raise RecordingError(f"{path}: not a CSV recording: {exc}") from None


def _lines(path: Path, fh) -> Iterator[tuple[int, str]]:
    """(number, line) with each line read at most MAX_LINE characters at a time, so a huge
    file without line ends (garbage, a binary) is refused after a megabyte, not read whole."""
    number = 0
    while line := fh.readline(MAX_LINE + 1):
        number += 1
        if len(line) > MAX_LINE:
            raise RecordingError(f"{path}:{number}: a line of over {MAX_LINE} characters; "
                                 f"expected a CSV recording ({','.join(COLUMNS)} rows)")
        yield number, line


def _read_csv(path: Path) -> Recording:
    metadata: dict[str, str] = {}
    rows: list[list[float]] = []
    with open(path, newline="", encoding="utf-8-sig") as fh:
        lines = _lines(path, fh)
        header = None
        for number, line in lines:
            if line.startswith("#"):
                key, sep, value = line[1:].strip().partition("=")
                if not sep or not key.strip():
                    raise RecordingError(f"{path}:{number}: metadata line must be "
                                         "'# key=value'")
                metadata[key.strip()] = value.strip()
                continue
            if line.strip():
                header = [c.strip() for c in next(csv.reader([line]))]
                break
        if header is None:
            raise RecordingError(f"{path}: no header line; expected {','.join(COLUMNS)}")
        if tuple(header[:4]) != COLUMNS:
            raise RecordingError(f"{path}:{number}: header {','.join(header)!r}; expected "
                                 f"the first columns to be {','.join(COLUMNS)}")
        for number, line in lines:
            if not line.strip():
                continue
            fields = next(csv.reader([line]))
            if len(fields) < 4:
                raise RecordingError(f"{path}:{number}: {len(fields)} fields, expected at "
                                     "least 4")
            try:
                rows.append([float(v) for v in fields[:4]])
            except ValueError:
                raise RecordingError(f"{path}:{number}: not a number in {line.strip()!r}") \
                    from None
    data = np.array(rows, dtype=float).reshape(-1, 4)
    return Recording(*data.T, metadata=metadata, source=str(path))


def write_csv(recording: Recording, path: Path) -> None:
    """The recording as CSV, written whole or not at all (`write_atomically`: a full disk
    leaves no truncated file). Raises OSError."""
    lines = [f"# {key}={value}\n" for key, value in recording.metadata.items()]
    lines.append(",".join(COLUMNS) + "\n")
    lines += [f"{row[0]:.6f},{row[1]:.9f},{row[2]:.6f},{row[3]:.6f}\n"
              for row in zip(recording.t, recording.q, recording.current,
                             recording.joint_torque, strict=True)]
    write_atomically(path, "".join(lines).encode())
