"""The virtual drive as EtherCAT slaves: an emulated slave controller per drive (registers,
SII, sync managers, FMMUs, watchdog), its firmware (state machine, CoE, process data) and the
line of slaves answering frames on a raw Ethernet interface."""

from sim_bus.ethercat.segment import Segment, serve

__all__ = ["Segment", "serve"]
