"""`bench`: the speed of the MPC tick and the cold solve against a plain numpy iLQR, and the
batched MPC for 7 and 32 joints (the measuring is `controller.benchmark`)."""

import argparse
import json
import sys

from controller.benchmark import run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench", description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--ticks", type=int, default=20000)
    parser.add_argument("--numpy-ticks", type=int, default=300)
    parser.add_argument("--joint-ticks", type=int, default=5000,
                        help="ticks of the batched MPC per joint count")
    args = parser.parse_args(argv)
    result = run(args.ticks, args.numpy_ticks, args.joint_ticks)
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
