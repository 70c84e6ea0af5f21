"""Print live values from actuatord: a minimal Zenoh subscriber using the documented schema.

    actuatord --sim --listen tcp/127.0.0.1:7447 &
    python examples/watch_elbow.py --connect tcp/127.0.0.1:7447

Any language works the same way: subscribe to {prefix}/state, {prefix}/command, ... and parse
the payload with protocol/telemetry.proto.
"""

import argparse
import json
import time

import zenoh

from protocol import telemetry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--prefix", default=telemetry.DEFAULT_PREFIX)
    parser.add_argument("--every", type=int, default=100, help="print one state in N")
    args = parser.parse_args()
    config = zenoh.Config()
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
    counter = {"state": 0}
    last_command = {}

    def on_state(sample: zenoh.Sample) -> None:
        counter["state"] += 1
        if counter["state"] % args.every:
            return
        s = telemetry.decode("State", sample.payload.to_bytes())
        c = last_command.get("value")
        reference = f"{c.reference_position:+.3f}" if c else "   ?  "
        print(f"t={s.t:8.3f} s  q={s.position:+.3f} rad (ref {reference})  "
              f"qd={s.velocity:+.3f} rad/s  i={s.motor_current:+.2f} A  "
              f"tau_j={s.joint_torque:+.2f} N.m  [{s.drive_state}]", flush=True)

    def on_command(sample: zenoh.Sample) -> None:
        last_command["value"] = telemetry.decode("Command", sample.payload.to_bytes())

    def on_fault(sample: zenoh.Sample) -> None:
        f = telemetry.decode("Fault", sample.payload.to_bytes())
        print(f"FAULT t={f.t:.3f} s [{f.source}] {f.cause} -> {f.action}", flush=True)

    with zenoh.open(config) as session:
        subscribers = [
            session.declare_subscriber(telemetry.key_expr(args.prefix, "state"), on_state),
            session.declare_subscriber(telemetry.key_expr(args.prefix, "command"), on_command),
            session.declare_subscriber(telemetry.key_expr(args.prefix, "fault"), on_fault)]
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            for subscriber in subscribers:
                subscriber.undeclare()


if __name__ == "__main__":
    main()
