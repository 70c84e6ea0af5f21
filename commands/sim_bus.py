"""`sim-bus`: run the virtual elbow drive on a CAN bus, or a line of them as EtherCAT slaves,
until SIGINT/SIGTERM."""

import argparse
import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Iterator, Sequence

from commands.bus_options import (
    add_bus_arguments,
    bus_config,
    check_drive_arguments,
    check_eds,
    ethercat_interface,
    load_esi_option,
    open_can_log,
)
from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.model_options import (
    add_model_argument,
    add_payload_arguments,
    check_payload,
    load_model_option,
    payload_from_args,
)
from commands.parsing import CommandParser, finite_float, non_negative_float, usage_error
from commands.sim_options import (
    add_virtual_drive_arguments,
    fault_schedule,
    parse_fault,
    with_truth_effects,
)
from driver.clock import WallClock, collector_off_the_cycle, keep_cpus_awake, lock_memory
from model.parameters import ActuatorModel, ModelFileError, Payload
from protocol.bus_spec import BusSpecError, is_ethercat
from robot.wiring import describe_bus, open_can_network
from sim_bus.canopen_node import CanOpenNode
from sim_bus.canopen_watchdogs import DEFAULT_SILENCE_TIMEOUT
from sim_bus.device import Cia402Device
from sim_bus.faults import Fault
from sim_bus.multicast import MulticastNetwork, MulticastReceiver
from sim_bus.plant import SensorNoise
from sim_bus.priority import answer_like_hardware

PROG = "sim-bus"
log = logging.getLogger(PROG)


def build_parser() -> CommandParser:
    parser = CommandParser(
        prog=PROG,
        description="A virtual CiA 402 drive for the TALOS elbow on a CAN bus, or a line of "
                    "them as EtherCAT slaves (--bus ethercat:IFACE --slaves N), its physics "
                    "from the actuator model. Each SYNC (each EtherCAT frame that writes the "
                    "slave's outputs) advances the physics one communication cycle period "
                    "(0x1006), so a master that waits for the answer runs it in lock-step. "
                    "SIGINT/SIGTERM stop it and print each drive's end state.")
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
    parser.add_argument("--silence-timeout", type=non_negative_float, metavar="S",
                        help="CAN: SYNC and RPDO silence after which the master counts as lost "
                             "and the drive quick-stops (0x6007), 0: off (default: "
                             f"{DEFAULT_SILENCE_TIMEOUT:g} s; the consumer heartbeat 0x1016 is "
                             "watched too). EtherCAT slaves watch their master with the sync "
                             "manager watchdog the master sets (100 ms; off in lock-step)")
    add_virtual_drive_arguments(parser, prefix="")
    parser.add_argument("--robot", metavar="FILE",
                        help="every drive of a robot file, commissioned for its joint: each CAN "
                             "drive on its bus at its node id, each EtherCAT line on its "
                             "interface with its joints in slave order (positions 0..N-1); "
                             "--inject-fault then takes JOINT:NAME@SECONDS")
    add_logging_argument(parser)
    return parser


def _serve_robot(args) -> int:
    """`sim-bus --robot FILE`: all the file's drives in this process until a signal, CAN
    drives on their buses, every EtherCAT line on its interface."""
    from commands.sim_options import parse_joint_fault
    from robot.description import RobotFileError, load_robot
    from robot.serving import serve_robot

    try:
        for option, key in (("--bus", "bus"), ("-i", "interface"), ("-c", "channel"),
                            ("--model", "model"), ("--can-log", "can_log"), ("--eds", "eds"),
                            ("--node-id", "node_id"), ("--slaves", "slaves"), ("--esi", "esi")):
            if getattr(args, key, None) is not None:
                raise ValueError(f"--robot and {option}: the robot file names each joint's bus, "
                                 "address, EDS and model")
        robot = load_robot(args.robot)
        for bus, joints in robot.buses().items():
            positions = sorted(joint.address for joint in joints)
            if is_ethercat(bus) and positions != list(range(len(joints))):
                raise ValueError(f"--robot {args.robot}: bus {bus}: slave positions "
                                 f"{positions}; sim-bus serves a line of consecutive slaves "
                                 f"0..{len(joints) - 1}")
        faults = [parse_joint_fault(text, [j.name for j in robot.joints])
                  for text in args.inject_fault]
    except (RobotFileError, BusSpecError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    try:
        served = serve_robot(robot, seed=args.seed, current_noise=args.current_noise,
                             torque_noise=args.torque_noise,
                             silence_timeout=_silence_timeout(args))
    except Exception as exc:  # python-can raises per interface: CanError, OSError, ImportError
        return job_error(PROG, f"cannot serve {args.robot}: {exc}")
    devices = dict(served.served)
    for name, fault, seconds in faults:
        devices[name].schedule(fault, seconds)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with _like_hardware():  # once every drive is ready: their answers are the hardware's
        print(f"sim-bus: {len(served.served)} drives of {robot.name} on "
              f"{', '.join(robot.buses())} ready", flush=True)
        served.serve_until(stop)
    print("sim-bus: stopped; " + ", ".join(
        f"{name} {device.cycle_count} cycles '{device.state.value}' at "
        f"{device.plant.position:.3f} rad" for name, device in served.served), flush=True)
    served.close()
    failed = served.failed_line()
    if failed is not None:
        return job_error(PROG, f"line {failed.bus} failed: {failed.failure}")
    return 0


def _line_faults(texts: Sequence[str], slaves: int) -> list[tuple[int | None, Fault, float]]:
    """`--inject-fault [SLAVE:]NAME@SECONDS` on a line: (position, or None for every slave,
    fault, s of drive time). ValueError names the option."""
    out = []
    for text in texts:
        position, sep, rest = text.rpartition(":")
        if sep and not (position.isdigit() and int(position) < slaves):
            raise ValueError(f"--inject-fault {text}: expected [SLAVE:]NAME@SECONDS with SLAVE "
                             f"a position 0..{slaves - 1}")
        fault, seconds = parse_fault(rest)
        out.append((int(position) if sep else None, fault, seconds))
    return out


def _serve_line(args: argparse.Namespace, interface: str, model: ActuatorModel,
                payload: Payload, faults: list[tuple[int | None, Fault, float]]) -> int:
    """`sim-bus --bus ethercat:IFACE`: --slaves virtual drives as a line on the interface,
    answering in this thread until a signal; then each slave's end state."""
    from protocol import ethercat as ec
    from sim_bus.embedded import make_device
    from sim_bus.ethercat.segment import serve

    devices = [make_device(model, payload, SensorNoise(
        current=args.current_noise, joint_torque=args.torque_noise, seed=args.seed + k),
        eds_path=args.eds, initial_position=args.initial_position)
        for k in range(args.slaves)]
    for position, fault, seconds in faults:
        for k, device in enumerate(devices):
            if position is None or position == k:
                device.schedule(fault, seconds)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    count = f"{args.slaves} slave{'s' if args.slaves > 1 else ''}"

    def ready(_) -> None:
        answer_like_hardware()  # this thread answers every frame
        print(f"sim-bus: {count} on {args.bus} ready ({model.name or model.source}, payload "
              f"{payload.mass} kg at ({payload.x}, {payload.y}) m)", flush=True)

    try:
        segment = serve(interface, devices, stop, esi_path=args.esi, on_ready=ready)
    except OSError as exc:
        return job_error(PROG, f"cannot open bus {args.bus}: {exc.strerror or exc} (a raw "
                               "socket on an existing interface needs root or CAP_NET_RAW)")
    states = []
    for k, (device, report) in enumerate(zip(devices, segment.report(), strict=True)):
        code = report["al_status_code"]
        states.append(f"slave {k} {report['cycles']} cycles, "
                      f"{ec.al_state_name(report['al_status'])}"
                      + (f" ({ec.al_status_name(code)})" if code else "")
                      + f", drive '{device.state.value}' at {report['position']:.3f} rad"
                      + (f", master lost: {report['master_loss']}"
                         if report["master_loss"] else ""))
    print(f"sim-bus: stopped after {segment.frames} frames; " + "; ".join(states), flush=True)
    return 0


@contextlib.contextmanager
def _like_hardware() -> Iterator[None]:
    """Serve as the hardware the drives stand in for answers, whatever the host does: at
    real-time priority (`answer_like_hardware`), the process's pages locked in memory, the
    CPUs kept out of sleep states (`driver.clock.keep_cpus_awake`), and
    Python's collector kept off what exists by now (`driver.clock`: a full collection walks
    every long-lived object, tens of ms during which no frame is answered, and a master
    declares the drives lost). Each refusal is one warning; the drives still serve."""
    for what, refused in (("real-time priority", answer_like_hardware()),
                          ("locked memory", lock_memory()),
                          ("CPU wake-up latency 0", keep_cpus_awake())):
        if refused is not None:
            log.warning("%s refused (%s): answers may come late on a busy host", what, refused)
    with collector_off_the_cycle():
        yield


def _silence_timeout(args) -> float | None:
    """The CAN drive's master-silence time (s, None: off): --silence-timeout (left None when
    not given, so that giving it with EtherCAT can be refused), else the default."""
    given = args.silence_timeout
    return (DEFAULT_SILENCE_TIMEOUT if given is None else given) or None


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    if args.robot is not None:
        return _serve_robot(args)
    try:
        check_drive_arguments(args)
        interface = ethercat_interface(args)
        if interface is not None and args.silence_timeout is not None:
            raise ValueError(f"--bus {args.bus} and --silence-timeout: EtherCAT slaves watch "
                             "their master with the sync manager watchdog the master sets")
        check_eds(args.eds, master=False, esi=load_esi_option(args))
        nominal = load_model_option(args.model)
        model = with_truth_effects(nominal, args.truth_effect)
        payload = payload_from_args(args)
        check_payload(nominal, payload)
        schedule = (fault_schedule(args) if interface is None
                    else _line_faults(args.inject_fault, args.slaves))
        limits = nominal.limits
        if args.initial_position is not None and not (
                limits.position_min <= args.initial_position <= limits.position_max):
            raise ValueError(f"--initial-position {args.initial_position:g}: expected a joint "
                             f"angle within the model's limits [{limits.position_min:g}, "
                             f"{limits.position_max:g}] rad")
    except (BusSpecError, ModelFileError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    if interface is not None:
        return _serve_line(args, interface, model, payload, schedule)

    config = bus_config(args)
    where = describe_bus(config)
    can_log = open_can_log(args) if args.can_log else None
    receiver = None
    try:
        if config.get("interface") == "udp_multicast" and can_log is None:
            # the lean path for the bus that stands in for CAN here (`sim_bus.multicast`)
            network = MulticastNetwork(config)
            receiver = MulticastReceiver([network])
        else:
            network = open_can_network(config, can_log)
    except Exception as exc:  # python-can raises per interface: CanError, OSError, ImportError
        if can_log is not None:
            can_log.stop()
        return job_error(PROG, f"cannot open bus {where}: {exc}")
    noise = SensorNoise(current=args.current_noise, joint_torque=args.torque_noise,
                        seed=args.seed)
    device = Cia402Device(model, payload, noise, eds_path=args.eds,
                          initial_position=args.initial_position, node_id=args.node_id)
    # a drive on a bus keeps its own clock, as hardware does: the wall clock
    node = CanOpenNode(network, args.node_id, device, clock=WallClock(),
                       silence_timeout=_silence_timeout(args))
    for fault, seconds in schedule:
        device.schedule(fault, seconds)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if receiver is not None:
        receiver.start()
    node.boot()
    with _like_hardware():
        print(f"sim-bus: node {args.node_id} on {where} ready ({model.name or model.source}, "
              f"payload {payload.mass} kg at ({payload.x}, {payload.y}) m)", flush=True)
        stop.wait()
    print(f"sim-bus: stopped after {device.cycle_count} SYNC cycles, drive state "
          f"'{device.state.value}' at {device.plant.position:.3f} rad", flush=True)
    if receiver is not None:
        receiver.stop()
    node.close()
    network.disconnect()
    if can_log is not None:
        can_log.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
