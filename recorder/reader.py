"""One entry for reading any recording: MCAP when the file starts with the MCAP magic bytes,
CSV otherwise (DESIGN.md's contract: every tool accepts both), checked for what no tool can use.
The content decides, not the name: an exported or renamed file reads the same."""

from pathlib import Path

from protocol.input_files import RECORDING_MAX, InputFileError, check_input_file, present
from recorder.csv_io import read_csv
from recorder.mcap_io import read_mcap
from recorder.mcap_records import MAGIC
from recorder.recording import Recording, RecordingError


def is_mcap(path: str | Path) -> bool:
    """Whether a recording file is MCAP (by its magic bytes) rather than CSV, after the checks
    every recording gets before it is read; any problem is one RecordingError line naming the
    file."""
    path = Path(path)
    try:
        if present(path):  # stat'ed before opening: a FIFO or a device is never read
            check_input_file(path, "a recording (MCAP or CSV)", RECORDING_MAX)
    except InputFileError as exc:
        raise RecordingError(str(exc)) from None
    try:
        with open(path, "rb") as fh:
            start = fh.read(len(MAGIC))
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise RecordingError(f"{path}: is a directory, expected a recording file (MCAP or "
                             "CSV)") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror}") from None
    if start == MAGIC:
        return True
    if path.suffix.lower() == ".mcap":
        raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic "
                             "bytes)")
    return False


def load_recording(path: str | Path) -> Recording:
    """Read and check a recording; any problem is one RecordingError line naming the file."""
    path = Path(path)
    if is_mcap(path):
        return read_mcap(path).check()
    return read_csv(path).check()
