"""Wire formats of the elbow drive: object dictionary, PDO layout, CiA 402 state machine.

No I/O here: everything is data and pure functions shared by the virtual drive and the master.
"""

from importlib.resources import files
from pathlib import Path


def eds_path() -> Path:
    """The EDS file shipped in the package (also the file a generic CANopen master loads)."""
    return Path(str(files("protocol") / "elbow_drive.eds"))


def esi_path() -> Path:
    """The ESI file shipped in the package: the same drive as the EDS, over EtherCAT (CoE)."""
    return Path(str(files("protocol") / "elbow_drive.xml"))
