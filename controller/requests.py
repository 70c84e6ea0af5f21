"""Requests from outside (Zenoh queryables): read the parameters, change a joint's reference or
cost weights (every joint of a robot has its own, at {prefix}/joints/{name}/reference and
.../weights; a robot of one joint also at {prefix}/reference and {prefix}/weights, see
`protocol.telemetry`). Validated here (in the queryable's thread, never the loop's), applied
by the loop at the start of a cycle, and every change, accepted or refused, leaves an audit
line on {prefix}/audit naming the joint.

A request is a small flat JSON object. Whatever a client sends, the work done for it is
bounded before any of it is parsed, so no body can hold the interpreter lock long enough to
stall the loop: a body over MAX_BODY bytes is refused from its length alone (never read); a body
with more than MAX_CONTAINERS opening brackets or MAX_SEPARATORS commas is refused after a
count in C (which bounds the nesting json.loads follows and the values it builds); and numbers
are handed to a hook that refuses any longer than MAX_NUMBER characters before Python converts
it. Reasons and audit lines quote at most a bounded excerpt of what was sent.
"""

import dataclasses
import datetime
import json
import logging
import math
from collections.abc import Callable
from typing import NamedTuple

from controller.loop import ControlLoop, MpcJoints
from controller.mpc import JointRow
from controller.problem import UnsafeWeights, Weights
from controller.reference import ReferenceError, reference_from_dict
from model.parameters import ActuatorModel, Payload

log = logging.getLogger(__name__)

MAX_WEIGHT = 1e6  # larger weights make the cost overflow near the limits
MAX_BODY = 64 * 1024  # bytes: a request is a few dozen; anything this big is not one
MAX_CONTAINERS = 8  # '{' and '[' in a body (strings included): a request is one flat object
MAX_SEPARATORS = 64  # ',' in a body (strings included): bounds the values json.loads builds
MAX_NUMBER = 40  # characters of one number: a double needs 17 digits, a sign, point, exponent
AUDIT_LINE_MAX = 1024  # bytes of one audit line, whatever was sent
REASON_MAX = 300  # characters of a refusal's reason (it may quote what was sent)



class RequestError(ValueError):
    """A request refused; the message is the reason sent back."""


class Body(NamedTuple):
    """A request's payload as a queryable sees it: its size, known without reading it, and
    how to read it."""

    size: int  # bytes
    read: Callable[[], bytes]


def cut(text: str, limit: int) -> str:
    """`text` shortened to at most `limit` characters, saying how long it was."""
    if len(text) <= limit:
        return text
    note = f"... ({len(text)} characters)"
    return text[:max(limit - len(note), 0)] + note


def parse_body(body: Body) -> object:
    """The JSON value of a request body, with every bound checked before parsing."""
    if body.size > MAX_BODY:
        raise RequestError(f"body of {body.size} bytes refused unread: a request is at most "
                           f"{MAX_BODY} bytes")
    try:
        text = body.read().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(f"not UTF-8 at byte {exc.start}") from None
    containers = text.count("{") + text.count("[")
    if containers > MAX_CONTAINERS:
        raise RequestError(f"{containers} '{{' or '[' refused unparsed: a request is one flat "
                           f"object (at most {MAX_CONTAINERS})")
    separators = text.count(",")
    if separators > MAX_SEPARATORS:
        raise RequestError(f"{separators} ',' refused unparsed: a request has a few fields (at "
                           f"most {MAX_SEPARATORS} commas)")
    try:
        return json.loads(text, parse_int=_integer, parse_float=_real)
    except RequestError:
        raise
    except ValueError as exc:
        raise RequestError(f"not JSON: {exc}") from None


def _checked_number(token: str) -> str:
    if len(token) > MAX_NUMBER:
        raise RequestError(f"a number of {len(token)} characters refused: at most {MAX_NUMBER}")
    return token


def _integer(token: str) -> int:
    return int(_checked_number(token))


def _real(token: str) -> float:
    return float(_checked_number(token))


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


def audit_line(time: str, t: float, request: str, body: Body, excerpt: bytes, accepted: bool,
               reason: str, joint: str = "") -> str:
    """One JSON audit line of at most AUDIT_LINE_MAX bytes: the payload is quoted as far as
    the bound allows (its full size is given), the reason cut to REASON_MAX; `joint` names
    the joint the request was for."""
    fields = {"time": time, "t": t, "request": request, "joint": joint,
              "payload_bytes": body.size,
              "payload": "", "accepted": accepted, "reason": cut(reason, REASON_MAX)}
    room = AUDIT_LINE_MAX - len(json.dumps(fields))
    quote = excerpt[:max(room, 0)].decode("utf-8", errors="replace")
    while quote:
        fields["payload"] = quote
        line = json.dumps(fields)
        if len(line) <= AUDIT_LINE_MAX:  # escapes can make a character up to 12 bytes
            return line
        quote = quote[:len(quote) // 2]
    fields["payload"] = ""
    return json.dumps(fields)


class RequestHandler:
    """The requests of one joint (`joint`: its index in the loop's robot) of a loop whose
    policy is the batched MPC: its parameters, reference and weights."""

    def __init__(self, loop: ControlLoop, joint: int, model: ActuatorModel, payload: Payload,
                 audit: Callable[[str], None]):
        if not isinstance(loop.policy, MpcJoints):
            raise TypeError("requests change the MPC's reference and weights: the loop's "
                            "policy is not the MPC")
        self.loop = loop
        self.index = joint
        self.name = loop.names[joint]
        self._batch = loop.policy.batch
        self.model = model
        self.payload = payload
        self.audit = audit

    @property
    def joint(self) -> JointRow:
        """The joint's problem in the batch (looked up each time: a new horizon rebuilds the
        batch)."""
        return self._batch.joints[self.index]

    def parameters(self, body: Body) -> dict:
        """The model, limits, settings and reference; a query carrying a body over the limit
        is refused (and audited) without reading it."""
        if body.size > MAX_BODY:
            return self._refuse("parameters", body, b"", f"body of {body.size} bytes refused "
                                f"unread: a parameters query needs none (at most {MAX_BODY})")
        joint = self.joint
        p = joint.parameters
        parameters = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)
                      if f.name != "effects"}
        parameters["effects"] = {name: p.effects.section(name) for name in p.effects.enabled()}
        return {"parameters": parameters,
                "limits": vars(self.model.limits), "provenance": self.model.provenance,
                "payload": vars(self.payload),
                "settings": {"horizon": joint.settings.horizon, "dt": joint.settings.dt,
                             "weights": vars(joint.settings.weights),
                             "sharpness": vars(joint.settings.sharpness),
                             "friction_sharpness": joint.settings.friction_sharpness,
                             "friction_sharpness_solved": joint.friction_sharpness_solved},
                "reference": {"kind": type(joint.reference).__name__.lower(),
                              **vars(joint.reference)}}

    def set_reference(self, body: Body) -> dict:
        return self._change("reference", body, self._reference)

    def set_weights(self, body: Body) -> dict:
        return self._change("weights", body, self._weights)

    def _reference(self, spec: object) -> Callable[[], None]:
        try:
            reference = reference_from_dict(spec, self.model.limits)
        except ReferenceError as exc:
            raise RequestError(str(exc)) from None
        joint = self.joint
        return lambda: joint.set_reference(reference)

    def _weights(self, spec: object) -> Callable[[], None]:
        changes = parse_weights(spec)
        try:  # checked against the weights in force, as a reference is against the limits
            self.joint.settings.with_weights(**changes).check_weights()
        except UnsafeWeights as exc:
            raise RequestError(str(exc)) from None
        loop, batch, name = self.loop, self._batch, self.name

        def apply() -> None:
            # again in the loop's thread: another change may have been applied in between
            joint = self.joint
            settings = joint.settings.with_weights(**changes)
            try:
                settings.check_weights()
            except UnsafeWeights as exc:
                loop.fault(loop.time, "request", f"joint {name}: weights refused: {exc}",
                           "weights unchanged")
                return
            batch.set_settings(joint, settings)

        return apply

    def _change(self, what: str, body: Body,
                build: Callable[[object], Callable[[], None]]) -> dict:
        excerpt = b""
        try:
            if body.size <= MAX_BODY:
                excerpt = body.read()
            spec = parse_body(Body(body.size, lambda: excerpt))
            change = build(spec)
        except RequestError as exc:
            return self._refuse(what, body, excerpt, str(exc))
        except Exception as exc:  # a bug here must cost one refused request, nothing more
            log.error("%s request failed: %s: %s", what, type(exc).__name__, cut(str(exc), 200))
            return self._refuse(what, body, excerpt, f"internal error ({type(exc).__name__})")
        self.loop.request(change)
        self._audit(what, body, excerpt, True, "applied at the next control cycle")
        return {"ok": True, what: spec}

    def _refuse(self, what: str, body: Body, excerpt: bytes, reason: str) -> dict:
        reason = cut(reason, REASON_MAX)
        self._audit(what, body, excerpt, False, reason)
        loop = self.loop
        # published by the loop's thread, like all its telemetry
        name = self.name
        loop.request(lambda: loop.fault(loop.time, "request",
                                        f"joint {name}: {what} refused: {reason}",
                                        f"{what} unchanged"))
        return {"ok": False, "reason": reason}

    def _audit(self, what: str, body: Body, excerpt: bytes, accepted: bool,
               reason: str) -> None:
        now = datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds")
        self.audit(audit_line(now, self.loop.time, what, body, excerpt, accepted, reason,
                              self.name))
