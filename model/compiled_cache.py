"""numba's on-disk cache, kept honest: numba checks only the timestamp of the file a function
is defined in, not of the files whose code it inlined. Compiled code that chained an older
version of another module (the effect registry, the physics, the solver) would still load after
an upgrade in place and silently compute with the old code. Each compiling package calls
`drop_stale` at import, before numba compiles anything (it compiles lazily)."""

import hashlib
from collections.abc import Iterable
from pathlib import Path


def drop_stale(folder: Path, pattern: str, sources: Iterable[Path], stamp: str) -> None:
    """Delete the compiled files `folder/pattern` unless `sources` are byte for byte the ones
    they were compiled from (their digest is kept in `folder/stamp`)."""
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sorted(sources)
                                     if p.exists())).hexdigest()
    recorded = folder / stamp
    try:
        if recorded.read_text() == digest:
            return
    except OSError:
        pass
    for path in folder.glob(pattern):
        path.unlink(missing_ok=True)
    try:
        folder.mkdir(exist_ok=True)
        recorded.write_text(digest)
    except OSError:
        pass  # a read-only install: numba then caches elsewhere or not at all
