"""iLQR with exponential barriers, the MPC loop at 1 kHz, Zenoh telemetry."""

import hashlib
from pathlib import Path


def _drop_stale_compiled_code() -> None:
    """numba's on-disk cache checks only the timestamp of the file a function is defined in,
    not of what it calls: the compiled MPC tick (mpc.py) chains the solver (ilqr.py), the
    action model and the physics (model/dynamics.py, model/effects.py). After an upgrade in
    place, a stale tick would still load and silently compute with the old physics (every
    cycle then falls back to the safety net). Drop this package's compiled cache whenever any
    of those sources differ from the ones it was compiled with; numba compiles lazily, after
    this runs (the package is imported before any of its modules)."""
    here = Path(__file__).parent
    model = here.parent / "model"
    sources = sorted([*here.glob("*.py"), model / "dynamics.py", model / "effects.py"])
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sources if p.exists())).hexdigest()
    folder = here / "__pycache__"
    stamp = folder / "compiled.sources.sha256"
    try:
        if stamp.read_text() == digest:
            return
    except OSError:
        pass
    for path in folder.glob("*.nb[ic]"):
        path.unlink(missing_ok=True)
    try:
        folder.mkdir(exist_ok=True)
        stamp.write_text(digest)
    except OSError:
        pass  # a read-only install: numba then caches elsewhere or not at all


_drop_stale_compiled_code()
