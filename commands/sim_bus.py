"""`sim-bus`: run the virtual elbow drive on a CAN bus until SIGINT/SIGTERM."""

import signal
import sys
import threading

from commands.options import (
    CommandParser,
    add_bus_arguments,
    add_logging_argument,
    add_model_argument,
    add_payload_arguments,
    add_virtual_drive_arguments,
    bus_config,
    check_drive_arguments,
    check_eds,
    check_payload,
    configure_logging,
    describe_bus,
    fault_schedule,
    finite_float,
    job_error,
    non_negative_float,
    open_bus_network,
    open_can_log,
    payload_from_args,
    usage_error,
    with_truth_effects,
)
from model.parameters import ModelFileError, load_model
from protocol.bus_spec import BusSpecError
from sim_bus.canopen_node import CanOpenNode
from sim_bus.canopen_watchdogs import DEFAULT_SILENCE_TIMEOUT
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise

PROG = "sim-bus"


def build_parser() -> CommandParser:
    parser = CommandParser(
        prog=PROG,
        description="A virtual CiA 402 drive for the TALOS elbow on a CAN bus, its physics from "
                    "the actuator model. Each SYNC advances the physics one communication cycle "
                    "period (0x1006), so a master that waits for the TPDOs runs it in lock-step.")
    add_bus_arguments(parser, sim=False)
    add_model_argument(parser)
    add_payload_arguments(parser)
    parser.add_argument("--initial-position", type=finite_float, metavar="RAD",
                        help="joint angle at power-on, within the model's position limits "
                             "(default: the hanging rest position)")
    parser.add_argument("--current-noise", type=non_negative_float, default=SensorNoise.current,
                        metavar="A", help="std of the current reading (default: %(default)s A)")
    parser.add_argument("--torque-noise", type=non_negative_float,
                        default=SensorNoise.joint_torque, metavar="NM",
                        help="std of the torque-sensor reading (default: %(default)s N.m)")
    parser.add_argument("--silence-timeout", type=non_negative_float,
                        default=DEFAULT_SILENCE_TIMEOUT, metavar="S",
                        help="SYNC and RPDO silence after which the master counts as lost and "
                             "the drive quick-stops (0x6007), 0: off (default: %(default)s s; "
                             "the consumer heartbeat 0x1016 is watched too)")
    add_virtual_drive_arguments(parser, prefix="")
    parser.add_argument("--robot", metavar="FILE",
                        help="every drive of a robot file, each on its bus at its node id, "
                             "commissioned for its joint (--inject-fault then takes "
                             "JOINT:NAME@SECONDS)")
    add_logging_argument(parser)
    return parser


def _serve_robot(args) -> int:
    """`sim-bus --robot FILE`: all the file's CAN drives in this process until a signal."""
    from commands.options import parse_joint_fault
    from commands.robot_file import RobotFileError, load_robot
    from driver.canopen_transport import open_network
    from model.parameters import Payload
    from protocol.bus_spec import is_ethercat
    from sim_bus.embedded import power_on

    try:
        for option, key in (("--bus", "bus"), ("-i", "interface"), ("-c", "channel"),
                            ("--model", "model"), ("--can-log", "can_log"), ("--eds", "eds")):
            if getattr(args, key, None) is not None:
                raise ValueError(f"--robot and {option}: the robot file names each joint's bus, "
                                 "EDS and model")
        robot = load_robot(args.robot)
        ethercat = [bus for bus in robot.buses() if is_ethercat(bus)]
        if ethercat:
            raise ValueError(f"--robot {args.robot}: bus {ethercat[0]}: EtherCAT slaves are "
                             "not served by this build")
        faults = [parse_joint_fault(text, [j.name for j in robot.joints])
                  for text in args.inject_fault]
    except (RobotFileError, BusSpecError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    networks, nodes = [], []
    try:
        for bus, joints in robot.buses().items():
            networks.append(open_network(bus, robot.bitrates.get(bus)))
            for joint in joints:
                index = robot.joints.index(joint)
                noise = SensorNoise(current=args.current_noise, joint_torque=args.torque_noise,
                                    seed=args.seed + index)
                nodes.append(power_on(networks[-1], joint.model, Payload(), noise,
                                      joint.address, eds_path=joint.eds, commissioned=True,
                                      silence_timeout=args.silence_timeout or None))
                for name, fault, seconds in faults:
                    if name == joint.name:
                        nodes[-1].device.schedule(fault, seconds)
    except Exception as exc:  # python-can raises per interface: CanError, OSError, ImportError
        for node in nodes:
            node.close()
        for network in networks:
            network.disconnect()
        return job_error(PROG, f"cannot serve {args.robot}: {exc}")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(f"sim-bus: {len(nodes)} drives of {robot.name} on {', '.join(robot.buses())} ready",
          flush=True)
    stop.wait()
    print("sim-bus: stopped; " + ", ".join(
        f"{joint.name} {node.device.cycle_count} cycles '{node.device.state.value}'"
        for joint, node in zip([j for js in robot.buses().values() for j in js], nodes,
                               strict=True)), flush=True)
    for node in nodes:
        node.close()
    for network in networks:
        network.disconnect()
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    if args.robot is not None:
        return _serve_robot(args)
    try:
        check_drive_arguments(args)
        check_eds(args.eds, master=False)
        nominal = load_model(args.model)
        model = with_truth_effects(nominal, args.truth_effect)
        payload = payload_from_args(args)
        check_payload(nominal, payload)
        schedule = fault_schedule(args)
        limits = nominal.limits
        if args.initial_position is not None and not (
                limits.position_min <= args.initial_position <= limits.position_max):
            raise ValueError(f"--initial-position {args.initial_position:g}: expected a joint "
                             f"angle within the model's limits [{limits.position_min:g}, "
                             f"{limits.position_max:g}] rad")
    except (BusSpecError, ModelFileError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    where = describe_bus(bus_config(args))
    can_log = open_can_log(args) if args.can_log else None
    try:
        network = open_bus_network(args, can_log)
    except Exception as exc:  # python-can raises per interface: CanError, OSError, ImportError
        if can_log is not None:
            can_log.stop()
        return job_error(PROG, f"cannot open bus {where}: {exc}")
    noise = SensorNoise(current=args.current_noise, joint_torque=args.torque_noise,
                        seed=args.seed)
    device = Cia402Device(model, payload, noise, eds_path=args.eds,
                          initial_position=args.initial_position, node_id=args.node_id)
    node = CanOpenNode(network, args.node_id, device,
                       silence_timeout=args.silence_timeout or None)
    for fault, seconds in schedule:
        device.schedule(fault, seconds)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    node.boot()
    print(f"sim-bus: node {args.node_id} on {where} ready ({model.name or model.source}, "
          f"payload {payload.mass} kg at ({payload.x}, {payload.y}) m)", flush=True)
    stop.wait()
    print(f"sim-bus: stopped after {device.cycle_count} SYNC cycles, drive state "
          f"'{device.state.value}'", flush=True)
    node.close()
    network.disconnect()
    if can_log is not None:
        can_log.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
