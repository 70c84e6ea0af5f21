"""`sim-bus`: run the virtual elbow drive on a CAN bus until SIGINT/SIGTERM."""

import argparse
import signal
import sys
import threading

import can
import canopen

from model.effects import with_truth_effects
from model.parameters import ModelFileError, load_model, parse_payload
from protocol.bus_spec import BusSpecError, parse_bus_spec
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.faults import Fault, parse_schedule
from sim_bus.plant import SensorNoise


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sim-bus",
        description="A virtual CiA 402 drive for the TALOS elbow on a CAN bus, its physics from "
                    "the actuator model. Each SYNC advances the physics one communication cycle "
                    "period (0x1006), so a master that waits for the TPDOs runs it in lock-step.")
    parser.add_argument("--bus", default="vcan0",
                        help="bus spec: vcan0 (SocketCAN), virtual:NAME, udp_multicast:GROUP[:PORT]"
                             " (default: vcan0)")
    parser.add_argument("--node-id", type=int, default=2, help="CANopen node id (default: 2)")
    parser.add_argument("--model", help="model TOML (default: the packaged paper defaults)")
    parser.add_argument("--payload-mass", type=float, default=0.0, metavar="KG",
                        help="point mass carried by the link (kg)")
    parser.add_argument("--payload-position", metavar="X,Y",
                        help="payload position in the link frame (m), e.g. 0,0.05")
    parser.add_argument("--initial-position", type=float, metavar="RAD",
                        help="joint angle at power-on (default: the hanging rest position)")
    parser.add_argument("--current-noise", type=float, default=SensorNoise.current,
                        metavar="A", help="std of the current reading (default: %(default)s A)")
    parser.add_argument("--torque-noise", type=float, default=SensorNoise.joint_torque,
                        metavar="NM", help="std of the torque-sensor reading "
                                           "(default: %(default)s N.m)")
    parser.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default: 0)")
    parser.add_argument("--truth-effect", action="append", default=[], metavar="NAME:K=V,...",
                        help="hidden effect in the drive's physics, e.g. "
                             "stribeck:breakaway_friction=1.5,velocity=0.05 (repeatable; "
                             "effects: stribeck, position_ripple, load_dependent_friction)")
    parser.add_argument("--inject-fault", action="append", default=[], metavar="NAME@SECONDS",
                        help="inject a fault at that drive time (repeatable): " + ", ".join(
                            f.name.lower() for f in Fault if f is not Fault.NONE)
                        + "; at run time, write its code to SDO 0x2010")
    return parser


def _usage_error(message: str) -> int:
    print(f"sim-bus: error: {message}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        parse_bus_spec(args.bus)
        model = with_truth_effects(load_model(args.model), args.truth_effect)
        payload = parse_payload(args.payload_mass, args.payload_position)
        schedule = [parse_schedule(text) for text in args.inject_fault]
    except (BusSpecError, ModelFileError, ValueError) as exc:
        return _usage_error(str(exc))
    if not 1 <= args.node_id <= 127:
        return _usage_error(f"--node-id {args.node_id}: expected 1..127")
    if args.current_noise < 0 or args.torque_noise < 0:
        return _usage_error("sensor noise must be >= 0")

    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # s; how long a shutdown waits for the receive thread
    try:
        network.connect(**parse_bus_spec(args.bus))
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        print(f"sim-bus: error: cannot open bus {args.bus!r}: {exc}", file=sys.stderr)
        return 1
    noise = SensorNoise(current=args.current_noise, joint_torque=args.torque_noise,
                        seed=args.seed)
    device = Cia402Device(model, payload, noise, initial_position=args.initial_position,
                          node_id=args.node_id)
    node = CanOpenNode(network, args.node_id, device)
    for fault, seconds in schedule:
        device.schedule(fault, seconds)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    node.boot()
    print(f"sim-bus: node {args.node_id} on {args.bus} ready ({model.name or model.source}, "
          f"payload {payload.mass} kg at ({payload.x}, {payload.y}) m)", flush=True)
    stop.wait()
    print(f"sim-bus: stopped after {device.cycle_count} SYNC cycles, drive state "
          f"'{device.state.value}'", flush=True)
    node.close()
    network.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())
