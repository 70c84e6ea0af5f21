"""`bus-bench`: how fast the master and the virtual drive run, in lock-step.

Prints one JSON object: SYNC cycles per second with both in this process on python-can's
`virtual` bus, and the SYNC -> TPDO sample latency and full SYNC -> TPDO -> RPDO cycle time with
`sim-bus` in a second process over `udp_multicast`.
"""

import json
import random
import subprocess
import sys
import time

import numpy as np

from commands.options import CommandParser, add_logging_argument, configure_logging, int_range
from driver.canopen_drive import CanOpenDrive, open_network


def _lockstep_in_process(cycles: int) -> float:
    from model.parameters import Payload, load_model
    from sim_bus.canopen_node import CanOpenNode
    from sim_bus.device import Cia402Device
    from sim_bus.plant import SensorNoise

    model = load_model()
    channel = f"virtual:bench-{random.getrandbits(32)}"
    sim_network = open_network(channel)
    sim = CanOpenNode(sim_network, 2, Cia402Device(model, Payload(), SensorNoise(), node_id=2),
                      lockstep=True)
    sim.boot()
    master = CanOpenDrive(open_network(channel), 2, velocity_limit=model.limits.velocity_max,
                          lockstep=True)
    try:
        master.start()
        start = time.perf_counter()
        for _ in range(cycles):
            master.sync()
            master.command_current(0.1)
        return cycles / (time.perf_counter() - start)
    finally:
        master.close()
        sim.close()
        sim_network.disconnect()


def _two_processes(cycles: int) -> dict:
    bus = f"udp_multicast:239.0.0.{random.randint(1, 250)}:{random.randint(20000, 60000)}"
    proc = subprocess.Popen([sys.executable, "-m", "commands.sim_bus", "--bus", bus],
                            stdout=subprocess.PIPE, text=True)
    try:
        if "ready" not in proc.stdout.readline():
            raise RuntimeError("sim-bus did not start")
        master = CanOpenDrive.open(bus, 2, velocity_limit=_velocity_limit())
        try:
            master.start()
            sample_latency, cycle_time = [], []
            for _ in range(cycles):
                t0 = time.perf_counter()
                master.sync()
                t1 = time.perf_counter()
                master.command_current(0.1)
                sample_latency.append(t1 - t0)
                cycle_time.append(time.perf_counter() - t0)
        finally:
            master.close()
    finally:
        proc.terminate()
        proc.wait(10)
    lat, cyc = np.array(sample_latency) * 1e6, np.array(cycle_time) * 1e6
    return {"sync_to_sample_median_us": round(float(np.median(lat)), 1),
            "sync_to_sample_p99_us": round(float(np.percentile(lat, 99)), 1),
            "sync_tpdo_rpdo_cycle_median_us": round(float(np.median(cyc)), 1),
            "sync_tpdo_rpdo_cycle_p99_us": round(float(np.percentile(cyc, 99)), 1),
            "cycles": cycles}


def _velocity_limit() -> float:
    from model.parameters import load_model

    return load_model().limits.velocity_max


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="bus-bench", description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int_range(1, 10_000_000), default=5000)
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(parser.prog, args.log_level)
    result = {"in_process_lockstep_cycles_per_s": round(_lockstep_in_process(args.cycles)),
              "udp_multicast_two_processes": _two_processes(args.cycles)}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
