"""Telemetry from Zenoh to Foxglove's WebSocket protocol (foxglove-sdk), with the same
protobuf schemas and bytes as on Zenoh and in the MCAP files. Each Zenoh key becomes the
Foxglove topic of the same name (`actuators/elbow/state`), created when the key first shows
up: the names recordings use, so one layout serves live data and files.

Viewers change the reference and the weights through two services,
`{prefix}/reference` and `{prefix}/weights`, which go through actuatord's queryables like
`dashboard set`: validated, applied at a cycle start, audited. A vanished actuatord (its
liveliness token gone) is shown as an error status in the viewer, also to viewers that connect
afterwards.

Viewers connect to `dashboard.foxglove_front`, which serves both subprotocol names on the
port and relays to the SDK's server on a loopback port of its own."""

import json
import logging
import threading
import time

import foxglove
import zenoh
from foxglove.websocket import Capability, ServiceRequest, StatusLevel

from dashboard.changes import CHANGES, NoAnswer, request_change
from dashboard.foxglove_front import ViewerFront
from dashboard.liveliness import watch_publisher
from protocol import telemetry

log = logging.getLogger(__name__)

PUBLISHER_STATUS = "publisher"  # id of the status message about actuatord's liveliness

# What the services take: actuatord validates the contents (one home for the rules); these
# schemas only give the viewer the shape of a request.
REQUEST_SCHEMAS = {
    telemetry.REFERENCE: {
        "title": "reference", "type": "object", "required": ["kind"],
        "description": "as `dashboard set reference`, e.g. "
                       "{\"kind\": \"setpoint\", \"position\": -1.0}",
        "properties": {"kind": {"type": "string"}},
        "additionalProperties": {"type": "number"}},
    telemetry.WEIGHTS: {
        "title": "weights", "type": "object", "minProperties": 1,
        "description": "cost weights to change, e.g. {\"position\": 300}",
        "additionalProperties": {"type": "number"}},
}
RESPONSE_SCHEMA = {"title": "accepted change", "type": "object",
                   "description": "{\"ok\": true, WHAT: the change as actuatord applies it}",
                   "properties": {"ok": {"type": "boolean"}}}


class ChangeFailed(RuntimeError):
    """Refused by actuatord, or no actuatord answered: the viewer shows why as the call's
    failure."""


class FoxgloveBridge:
    """The bridge on `port` at `host` (0: the kernel's pick; `ports` are the ones served),
    and on each of `extra_ports` too. Raises OSError when a port cannot be listened on."""

    def __init__(self, session: zenoh.Session, key: str, prefix: str = telemetry.DEFAULT_PREFIX,
                 host: str = "127.0.0.1", port: int = 8765, extra_ports: list[int] = ()):
        self.session = session
        self.prefix = prefix
        self.server = foxglove.start_server(
            name="actuator-link", host="127.0.0.1", port=0, capabilities=[Capability.Services],
            services=[self._service(what) for what in CHANGES])
        self._lock = threading.Lock()
        self._channels: dict[str, foxglove.Channel] = {}
        self._status: str | None = None  # the status frame a new viewer is sent
        self._status_lock = threading.Lock()  # liveliness callbacks and start-up both set it
        self.forwarded = 0
        # actuatord's topics exist before their first message, so a viewer can subscribe to
        # faults and the audit before there are any
        for topic in [*telemetry.TOPICS, telemetry.AUDIT]:
            if zenoh.KeyExpr(key).intersects(zenoh.KeyExpr(telemetry.key_expr(prefix, topic))):
                self._channel(telemetry.key_expr(prefix, topic))
        self._subscriber = session.declare_subscriber(key, self._on_sample)
        self._publish_status(f"waiting for actuatord under {prefix}", StatusLevel.Warning)
        try:
            self.front = ViewerFront(self.server.port, host, [port, *extra_ports],
                                     lambda: self._status)
        except OSError:
            self._subscriber.undeclare()
            self.server.stop()
            raise
        self._liveliness = watch_publisher(session, prefix, self._on_liveliness)

    @property
    def port(self) -> int:
        return self.front.ports[0]

    @property
    def ports(self) -> list[int]:
        return self.front.ports

    def _publish_status(self, message: str, level: StatusLevel) -> None:
        with self._status_lock:
            self._status = json.dumps({"op": "status", "level": int(level), "message": message,
                                       "id": PUBLISHER_STATUS})
            self.server.publish_status(message, level, PUBLISHER_STATUS)

    def _channel(self, key: str) -> foxglove.Channel | None:
        with self._lock:
            channel = self._channels.get(key)
            if channel is not None:
                return channel
            name = key.rsplit("/", 1)[-1]
            if name == telemetry.AUDIT:
                channel = foxglove.Channel(key, message_encoding="json", schema=foxglove.Schema(
                    name=telemetry.AUDIT_SCHEMA_NAME, encoding="jsonschema",
                    data=json.dumps(telemetry.AUDIT_SCHEMA).encode()))
            elif name in telemetry.TOPICS:
                message = telemetry.TOPICS[name]
                channel = foxglove.Channel(
                    key, message_encoding="protobuf",
                    schema=foxglove.Schema(name=telemetry.schema_name(message),
                                           encoding="protobuf",
                                           data=telemetry.file_descriptor_set()))
            else:
                return None
            self._channels[key] = channel
            return channel

    def _on_sample(self, sample: zenoh.Sample) -> None:
        channel = self._channel(str(sample.key_expr))
        if channel is not None:
            channel.log(sample.payload.to_bytes(), log_time=time.time_ns())
            self.forwarded += 1

    def _on_liveliness(self, alive: bool) -> None:
        if alive:
            with self._status_lock:
                self._status = None
                self.server.remove_status([PUBLISHER_STATUS])
        else:
            self._publish_status(
                f"actuatord under {self.prefix} vanished: its liveliness token is gone; the "
                f"data shown is its last", StatusLevel.Error)

    def _service(self, what: str) -> foxglove.Service:
        def json_schema(name: str, body: dict) -> foxglove.MessageSchema:
            return foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
                name=name, encoding="jsonschema", data=json.dumps(body).encode()))

        def handler(request: ServiceRequest) -> bytes:
            try:
                answers = request_change(self.session, self.prefix, what, request.payload)
            except NoAnswer as exc:
                raise ChangeFailed(str(exc)) from None
            refused = [a.reason for a in answers if not a.accepted]
            if refused:
                raise ChangeFailed(f"{what} refused: {'; '.join(refused)}")
            return json.dumps({"ok": True, what: answers[0].change}).encode()

        return foxglove.Service(
            name=telemetry.key_expr(self.prefix, what), handler=handler,
            schema=foxglove.ServiceSchema(
                name=f"actuator.set_{what}",
                request=json_schema(f"actuator.{what}_request", REQUEST_SCHEMAS[what]),
                response=json_schema(f"actuator.{what}_response", RESPONSE_SCHEMA)))

    def close(self) -> None:
        self._liveliness.undeclare()
        self._subscriber.undeclare()
        self.front.close()
        self.server.stop()
