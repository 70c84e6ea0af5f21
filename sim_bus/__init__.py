"""A virtual CiA 402 elbow drive on a python-can bus, its physics from `model/`."""

from pathlib import Path

from model.compiled_cache import drop_stale

# the compiled line batch (line_physics.py) chains the physics (model/dynamics.py,
# model/effects.py) and freezes constants of the plant, the device and the object units: after
# an upgrade in place a stale batch would drive the virtual joints with the old physics
_HERE = Path(__file__).parent
drop_stale(_HERE / "__pycache__", "line_physics.*.nb[ic]",
           [_HERE / "line_physics.py", _HERE / "plant.py", _HERE / "device.py",
            _HERE.parent / "model" / "dynamics.py", _HERE.parent / "model" / "effects.py",
            _HERE.parent / "protocol" / "objects.py"], "line_physics.sources.sha256")
