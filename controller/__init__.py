"""iLQR with exponential barriers, the MPC loop at 1 kHz, Zenoh telemetry."""

from pathlib import Path

from model.compiled_cache import drop_stale

# the compiled MPC tick (mpc.py) chains the solver (ilqr.py), the action model and the physics
# (model/dynamics.py, model/effects.py): after an upgrade in place a stale tick would compute
# with the old physics and every cycle would fall back to the safety net
_HERE = Path(__file__).parent
drop_stale(_HERE / "__pycache__", "*.nb[ic]",
           [*_HERE.glob("*.py"), _HERE.parent / "model" / "dynamics.py",
            _HERE.parent / "model" / "effects.py"], "compiled.sources.sha256")
