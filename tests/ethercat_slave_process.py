"""Virtual EtherCAT slaves for the tests: `ethercat_slave_process.py IFACE N [--seed S]`.
Prints `ready` once the interface is open, serves until SIGTERM, then prints one JSON line
with each slave's end state (AL status, device state, brake, master loss, cycles)."""

import argparse
import json
import signal
import threading

from model.parameters import load_model
from sim_bus.device import Cia402Device
from sim_bus.ethercat.segment import Segment, open_socket, run
from sim_bus.plant import SensorNoise


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("interface")
    parser.add_argument("slaves", type=int)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = load_model()
    devices = [Cia402Device(model, noise=SensorNoise(seed=args.seed + k))
               for k in range(args.slaves)]
    segment = Segment(devices)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    sock = open_socket(args.interface)
    print("ready", flush=True)
    run(sock, segment, stop)
    report = []
    for esc, firmware in zip(segment.escs, segment.firmwares, strict=True):
        device = firmware.device
        report.append({
            "al_status": esc.al_status,
            "al_status_code": esc.memory[0x0134] | esc.memory[0x0135] << 8,
            "state": device.state.name,
            "brake_engaged": device.brake_engaged,
            "master_loss": device.master_loss,
            "cycles": firmware.cycles,
            "position": device.plant.position,
        })
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    main()
