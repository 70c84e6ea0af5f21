"""Requests from outside (Zenoh queryables): read the parameters, change the reference or the
cost weights. Validated here, applied by the loop at the start of a cycle, and every change,
accepted or refused, leaves an audit line on {prefix}/audit."""

import dataclasses
import datetime
import json
import math
from collections.abc import Callable

from controller.loop import ControlLoop
from controller.mpc import Mpc
from controller.problem import Weights
from controller.reference import ReferenceError, reference_from_dict
from model.parameters import ActuatorModel, Payload

MAX_WEIGHT = 1e6  # larger weights make the cost overflow near the limits


class RequestError(ValueError):
    """A request refused; the message is the reason sent back."""


def parse_weights(spec: object) -> dict[str, float]:
    if not isinstance(spec, dict) or not spec:
        raise RequestError("weights must be a JSON object such as {\"position\": 300}")
    out = {}
    for name, value in spec.items():
        if name not in Weights.__dataclass_fields__:
            raise RequestError(f"unknown weight {name!r}; expected one of "
                               f"{', '.join(Weights.__dataclass_fields__)}")
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
                value):
            raise RequestError(f"weight {name}: expected a finite number, got {value!r}")
        if not 0 <= value <= MAX_WEIGHT:
            raise RequestError(f"weight {name}: {value} is out of range [0, {MAX_WEIGHT:g}]")
        out[name] = float(value)
    return out


class RequestHandler:
    def __init__(self, loop: ControlLoop, mpc: Mpc, model: ActuatorModel, payload: Payload,
                 audit: Callable[[dict], None]):
        self.loop = loop
        self.mpc = mpc
        self.model = model
        self.payload = payload
        self.audit = audit

    def parameters(self, _: bytes | None) -> dict:
        mpc = self.mpc
        return {"parameters": dataclasses.asdict(mpc.parameters),
                "limits": vars(self.model.limits), "provenance": self.model.provenance,
                "payload": vars(self.payload),
                "settings": {"horizon": mpc.settings.horizon, "dt": mpc.settings.dt,
                             "weights": vars(mpc.settings.weights),
                             "sharpness": vars(mpc.settings.sharpness),
                             "friction_sharpness": mpc.settings.friction_sharpness},
                "reference": {"kind": type(mpc.reference).__name__.lower(),
                              **vars(mpc.reference)}}

    def set_reference(self, payload: bytes | None) -> dict:
        return self._change("reference", payload, self._reference)

    def set_weights(self, payload: bytes | None) -> dict:
        return self._change("weights", payload, self._weights)

    def _reference(self, spec: object) -> Callable[[], None]:
        try:
            reference = reference_from_dict(spec, self.model.limits)
        except ReferenceError as exc:
            raise RequestError(str(exc)) from None
        mpc = self.mpc
        return lambda: mpc.set_reference(reference)

    def _weights(self, spec: object) -> Callable[[], None]:
        changes = parse_weights(spec)
        mpc = self.mpc
        return lambda: mpc.set_settings(mpc.settings.with_weights(**changes))

    def _change(self, what: str, payload: bytes | None,
                build: Callable[[object], Callable[[], None]]) -> dict:
        text = (payload or b"").decode("utf-8", errors="replace")
        try:
            try:
                spec = json.loads(text)
            except ValueError as exc:
                raise RequestError(f"not JSON: {exc}") from None
            change = build(spec)
        except RequestError as exc:
            self._audit(what, text, False, str(exc))
            self.loop.fault(self.loop.time, "request", f"{what} refused: {exc}",
                            f"{what} unchanged")
            return {"ok": False, "reason": str(exc)}
        self.loop.request(change)
        self._audit(what, text, True, "applied at the next control cycle")
        return {"ok": True, what: spec}

    def _audit(self, what: str, text: str, accepted: bool, reason: str) -> None:
        self.audit({"time": datetime.datetime.now(datetime.UTC).isoformat(
                        timespec="milliseconds"),
                    "t": self.loop.time, "request": what, "payload": text, "accepted": accepted,
                    "reason": reason})
