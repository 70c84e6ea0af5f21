"""Commands run one after the other in one process (python -m tests.command_batch JOBS.json
OUT.json): JOBS a list of [MODULE, ARG, ...] (`commands.recorder`, `commands.identify`, ...),
each module's `main(args)` called as its console script calls it; OUT a list of
{"code": exit code, "stderr": what it wrote there}, in the jobs' order. A job that fails
stops its batch (the later ones use its files). A process of its own pays the imports and
the compiled code once for the batch: a test's setup recording several experiments spent
most of its time starting interpreters."""

import contextlib
import importlib
import io
import json
import sys
import traceback
from pathlib import Path


def main(argv: list[str]) -> int:
    jobs = json.loads(Path(argv[0]).read_text())
    results = []
    for module, *args in jobs:
        errors = io.StringIO()
        try:
            with contextlib.redirect_stderr(errors):
                code = importlib.import_module(module).main(args)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except Exception:
            code, errors = 1, io.StringIO(traceback.format_exc())
        results.append({"code": code, "stderr": errors.getvalue()})
        if code:
            break
    Path(argv[1]).write_text(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
