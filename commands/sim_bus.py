"""`sim-bus`: run the virtual elbow drive on a CAN bus until SIGINT/SIGTERM."""

import argparse
import signal
import sys
import threading

import can
import canopen

from commands.options import (
    add_bus_arguments,
    add_model_argument,
    add_payload_arguments,
    add_virtual_drive_arguments,
    check_drive_arguments,
    fault_schedule,
    payload_from_args,
    usage_error,
    with_truth_effects,
)
from model.parameters import ModelFileError, load_model
from protocol.bus_spec import BusSpecError, parse_bus_spec
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise

PROG = "sim-bus"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="A virtual CiA 402 drive for the TALOS elbow on a CAN bus, its physics from "
                    "the actuator model. Each SYNC advances the physics one communication cycle "
                    "period (0x1006), so a master that waits for the TPDOs runs it in lock-step.")
    add_bus_arguments(parser, sim=False)
    add_model_argument(parser)
    add_payload_arguments(parser)
    parser.add_argument("--initial-position", type=float, metavar="RAD",
                        help="joint angle at power-on (default: the hanging rest position)")
    parser.add_argument("--current-noise", type=float, default=SensorNoise.current,
                        metavar="A", help="std of the current reading (default: %(default)s A)")
    parser.add_argument("--torque-noise", type=float, default=SensorNoise.joint_torque,
                        metavar="NM", help="std of the torque-sensor reading "
                                           "(default: %(default)s N.m)")
    add_virtual_drive_arguments(parser, prefix="")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_drive_arguments(args)
        model = with_truth_effects(load_model(args.model), args.truth_effect)
        payload = payload_from_args(args)
        schedule = fault_schedule(args)
    except (BusSpecError, ModelFileError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    if not 1 <= args.node_id <= 127:
        return usage_error(PROG, f"--node-id {args.node_id}: expected 1..127")
    if args.current_noise < 0 or args.torque_noise < 0:
        return usage_error(PROG, "sensor noise must be >= 0")

    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # s; how long a shutdown waits for the receive thread
    try:
        network.connect(**parse_bus_spec(args.bus))
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        print(f"{PROG}: error: cannot open bus {args.bus!r}: {exc}", file=sys.stderr)
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
