"""Change requests to actuatord (the reference, the cost weights) through its Zenoh queryables.
`dashboard set` and the Foxglove bridge's services both go through `request_change`, so every
change from any viewer is validated, applied at a cycle start and audited by actuatord in the
same way."""

import json
from dataclasses import dataclass

import zenoh

from protocol import telemetry

CHANGES = (telemetry.REFERENCE, telemetry.WEIGHTS)
TIMEOUT_S = 5.0  # an actuatord answers within one cycle; this covers a loaded host


class NoAnswer(RuntimeError):
    """No actuatord answered (none running under the prefix, or the ACL denies the query)."""


@dataclass(frozen=True)
class Answer:
    """One actuatord's answer: accepted with the change as applied, or refused with why."""

    accepted: bool
    change: object  # the request as actuatord understood it (accepted only)
    reason: str  # why it was refused (refused only)

    @classmethod
    def from_reply(cls, what: str, data: bytes) -> "Answer":
        reply = json.loads(data)
        if reply.get("ok"):
            return cls(True, reply.get(what), "")
        return cls(False, None, str(reply.get("reason")))


def request_change(session: zenoh.Session, prefix: str, what: str,
                   payload: bytes | str) -> list[Answer]:
    """Send one change request and collect every answer. Raises NoAnswer if nobody answered."""
    if what not in CHANGES:
        raise ValueError(f"unknown change {what!r}; expected one of {', '.join(CHANGES)}")
    key = telemetry.key_expr(prefix, what)
    answers = [Answer.from_reply(what, reply.ok.payload.to_bytes())
               for reply in session.get(key, payload=payload, timeout=TIMEOUT_S)
               if reply.ok is not None]
    if not answers:
        raise NoAnswer(f"no actuatord answered on {key}")
    return answers
