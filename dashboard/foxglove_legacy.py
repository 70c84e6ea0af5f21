"""A second WebSocket port for viewers that offer only the `foxglove.websocket.v1` subprotocol
(Lichtblick before its December 2025 release, older Foxglove Studio builds, clients written for
ros-foxglove-bridge 0.8). foxglove-sdk 0.30 accepts only `foxglove.sdk.v1` (`foxglove.sdk.v1.1`)
and refuses the old name with HTTP 400, with no option to allow it. The two names carry the same
protocol (Foxglove's stated position; Lichtblick added the new name by adding the string), so
the relay passes every frame through unchanged between the old name and the bridge."""

import asyncio
import logging
import threading

import websockets
from websockets.asyncio.server import ServerConnection

log = logging.getLogger(__name__)

LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
SDK_SUBPROTOCOL = "foxglove.sdk.v1"


class LegacyRelay:
    """Serves `foxglove.websocket.v1` on host:port, one upstream connection to the bridge at
    ws://upstream_host:upstream_port per viewer."""

    def __init__(self, upstream_host: str, upstream_port: int, host: str, port: int):
        # a bridge bound to every interface is reached on loopback
        loopback = upstream_host in ("0.0.0.0", "::")
        self._upstream = f"ws://{'127.0.0.1' if loopback else upstream_host}:{upstream_port}"
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self.port = port
        self._thread = threading.Thread(target=self._loop.run_until_complete,
                                        args=(self._serve(host, port),), name="foxglove-legacy",
                                        daemon=True)
        self._thread.start()
        self._ready.wait(10)

    async def _serve(self, host: str, port: int) -> None:
        self._stop = asyncio.Event()
        async with websockets.serve(self._relay, host, port, subprotocols=[LEGACY_SUBPROTOCOL],
                                    max_size=None) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop.wait()

    async def _relay(self, viewer: ServerConnection) -> None:
        try:
            async with websockets.connect(self._upstream, subprotocols=[SDK_SUBPROTOCOL],
                                          max_size=None, compression=None) as bridge:
                pumps = [asyncio.create_task(self._pump(viewer, bridge)),
                         asyncio.create_task(self._pump(bridge, viewer))]
                await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for pump in pumps:
                    pump.cancel()
        except (OSError, websockets.WebSocketException) as exc:
            log.warning("legacy viewer %s: %s", viewer.remote_address, exc)

    @staticmethod
    async def _pump(source, sink) -> None:
        """Until either side closes (the relay then closes the other)."""
        try:
            async for frame in source:
                await sink.send(frame)
        except websockets.ConnectionClosed:
            pass

    def close(self) -> None:
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)
