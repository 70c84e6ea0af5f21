"""`bench`: the speed of the MPC tick and the cold solve against a plain numpy iLQR, the
batched MPC for 1, 7 and 32 joints and for talos_32's own problem on one and two threads, the
vectorised kernel beside the scalar one (the measuring is `controller.benchmark`), and the
master's own cost per cycle for 1, 7 and 32 joints with the MPC left out (`robot.bench`)."""

import json
import sys

from commands.first_run import CompileNotice
from commands.log_options import add_logging_argument, configure_logging, reports_failures
from commands.parsing import CommandParser, doc_description, int_range
from controller.benchmark import run
from robot.bench import MASTER_JOINT_COUNTS, TALOS, robot_problems
from robot.bench import run as master_cost


@reports_failures("bench")
def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="bench", description=doc_description(__doc__))
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--ticks", type=int_range(1, 10_000_000), default=20000)
    parser.add_argument("--numpy-ticks", type=int_range(1, 10_000_000), default=300)
    parser.add_argument("--joint-ticks", type=int_range(1, 10_000_000), default=5000,
                        help="ticks of the batched MPC per joint count, thread count and kernel")
    parser.add_argument("--master-cycles", type=int_range(10, 10_000_000), default=3000,
                        help="cycles of the robot loop per joint count for the master's own "
                             "cost (default: %(default)s)")
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(parser.prog, args.log_level)
    # one tick of everything first: the compiling (a first run's 30 s and more) is said, and
    # stays out of the figures
    with CompileNotice(parser.prog):
        run(1, 1, 1)
    def progress(stage: str) -> None:
        print(f"bench: {stage} ...", file=sys.stderr, flush=True)

    result = run(args.ticks, args.numpy_ticks, args.joint_ticks, progress=progress,
                 robot=(TALOS.stem, robot_problems()))
    progress(f"the master's own cost (MPC excluded) for {', '.join(map(str, MASTER_JOINT_COUNTS))}"
             f" joints on a line linked in this process: {args.master_cycles} cycles each")
    result["master"] = master_cost(args.master_cycles)
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
