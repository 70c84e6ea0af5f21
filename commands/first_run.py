"""The first run's wait, said: numba compiles the solver and the physics on the first run after
an install or a change (about 30 s here, 90 s on a loaded host; cached in `__pycache__` or
NUMBA_CACHE_DIR afterwards, when the same start takes 2-3 s), which otherwise looks like a
command that hangs."""

import sys
import threading
from types import TracebackType

# s of start-up after which the wait is said: a start from the cache is well under this
NOTICE_AFTER = 3.0


class CompileNotice:
    """One line on stderr, `PROG: compiling ... (first run only)`, if the work it surrounds is
    still going after NOTICE_AFTER seconds; nothing when it is quick (the code was cached).
    Use as a context manager, or call `done()` where the slow part ends."""

    def __init__(self, prog: str, after: float = NOTICE_AFTER):
        self._timer = threading.Timer(after, self._say, args=(prog,))
        self._timer.daemon = True
        self._timer.start()

    @staticmethod
    def _say(prog: str) -> None:
        print(f"{prog}: compiling the controller and physics code with numba (first run "
              "after an install or an update only; cached afterwards) ...", file=sys.stderr,
              flush=True)

    def done(self) -> None:
        self._timer.cancel()

    def __enter__(self) -> "CompileNotice":
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None) -> None:
        self.done()
