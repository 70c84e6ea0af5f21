"""`bench`: the speed of the MPC tick and the cold solve against a plain numpy iLQR, and the
batched MPC for 1, 7 and 32 joints on one and two threads, the vectorised kernel beside the
scalar one (the measuring is `controller.benchmark`)."""

import json
import sys

from commands.first_run import CompileNotice
from commands.log_options import add_logging_argument, configure_logging, reports_failures
from commands.parsing import CommandParser, doc_description, int_range
from controller.benchmark import run


@reports_failures("bench")
def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="bench", description=doc_description(__doc__))
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--ticks", type=int_range(1, 10_000_000), default=20000)
    parser.add_argument("--numpy-ticks", type=int_range(1, 10_000_000), default=300)
    parser.add_argument("--joint-ticks", type=int_range(1, 10_000_000), default=5000,
                        help="ticks of the batched MPC per joint count, thread count and kernel")
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(parser.prog, args.log_level)
    # one tick of everything first: the compiling (a first run's 30 s and more) is said, and
    # stays out of the figures
    with CompileNotice(parser.prog):
        run(1, 1, 1)
    result = run(args.ticks, args.numpy_ticks, args.joint_ticks,
                 progress=lambda stage: print(f"bench: {stage} ...", file=sys.stderr,
                                              flush=True))
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
