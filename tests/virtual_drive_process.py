"""A virtual drive in its own process for the two-process tests, built from the library as
`sim-bus` builds it, with the EDS, payload and master-silence timeout a test needs:

    python -m tests.virtual_drive_process BUS NODE_ID [--eds FILE] [--payload-mass KG
        --payload-position X,Y]

Prints "ready" once the drive has booted; runs until SIGTERM.
"""

import argparse
import signal
import sys
import threading

import canopen

from commands.model_options import parse_payload
from driver.clock import WallClock
from model.parameters import load_model
from protocol.bus_spec import parse_bus_spec
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise
from sim_bus.priority import answer_like_hardware


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("bus")
    parser.add_argument("node_id", type=int)
    parser.add_argument("--eds")
    parser.add_argument("--payload-mass", type=float, default=0.0)
    parser.add_argument("--payload-position")
    args = parser.parse_args()
    network = canopen.Network()
    network.connect(**parse_bus_spec(args.bus))
    device = Cia402Device(load_model(), parse_payload(args.payload_mass, args.payload_position),
                          SensorNoise(), eds_path=args.eds, node_id=args.node_id)
    node = CanOpenNode(network, args.node_id, device, clock=WallClock())
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    node.boot()
    answer_like_hardware()
    print("ready", flush=True)
    stop.wait()
    node.close()
    network.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())
