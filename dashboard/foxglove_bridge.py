"""Telemetry from Zenoh to Foxglove's WebSocket protocol (foxglove-sdk), with the same
protobuf schemas and bytes as on Zenoh and in the MCAP files: a Foxglove topic per key
(`/actuators/elbow/state`, ...), created when the key first shows up."""

import logging
import threading
import time

import foxglove
import zenoh

from protocol import telemetry

log = logging.getLogger(__name__)


class FoxgloveBridge:
    def __init__(self, session: zenoh.Session, key: str, host: str = "127.0.0.1",
                 port: int = 8765):
        self.server = foxglove.start_server(name="actuator-link", host=host, port=port)
        self._lock = threading.Lock()
        self._channels: dict[str, foxglove.Channel] = {}
        self.forwarded = 0
        self._subscriber = session.declare_subscriber(key, self._on_sample)

    def _channel(self, key: str) -> foxglove.Channel | None:
        with self._lock:
            channel = self._channels.get(key)
            if channel is not None:
                return channel
            name = key.rsplit("/", 1)[-1]
            if name == telemetry.AUDIT:
                channel = foxglove.Channel(f"/{key}", message_encoding="json")
            elif name in telemetry.TOPICS:
                message = telemetry.TOPICS[name]
                channel = foxglove.Channel(
                    f"/{key}", message_encoding="protobuf",
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

    def close(self) -> None:
        self._subscriber.undeclare()
        self.server.stop()
