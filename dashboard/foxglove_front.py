"""The port viewers connect to. foxglove-sdk 0.30's server accepts only the `foxglove.sdk.v1`
subprotocol and refuses `foxglove.websocket.v1` (what `@foxglove/ws-protocol`, Lichtblick up to
1.21 and clients written for ros-foxglove-bridge offer) with HTTP 400, with no option to allow
it, and it sends a status only to the viewers connected when it is published. The two names
carry the same protocol (Foxglove's stated position; Lichtblick added the new name by adding
the string), so this front serves both names on one port and passes every frame through
unchanged to the SDK's server on a loopback port of its own, one upstream connection per
viewer; after the server's first frame (serverInfo) it replays the bridge's current status, so
a viewer that connects after actuatord vanished is told so."""

import asyncio
import logging
import threading
from collections.abc import Callable

import websockets
from websockets.asyncio.server import ServerConnection

log = logging.getLogger(__name__)

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
SUBPROTOCOLS = [SDK_SUBPROTOCOL, LEGACY_SUBPROTOCOL]


class ViewerFront:
    """Serves both subprotocols on each of `ports` (at `host`; port 0: the kernel's pick, see
    `ports` afterwards), relaying to the SDK server at ws://127.0.0.1:upstream_port.
    `status()` gives the status frame (JSON text) to replay to a new viewer, or None."""

    def __init__(self, upstream_port: int, host: str, ports: list[int],
                 status: Callable[[], str | None]):
        self._upstream = f"ws://127.0.0.1:{upstream_port}"
        self._status = status
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._error: OSError | None = None
        self.ports = list(ports)
        self._thread = threading.Thread(target=self._loop.run_until_complete,
                                        args=(self._serve(host),), name="foxglove-front",
                                        daemon=True)
        self._thread.start()
        self._ready.wait(10)
        if self._error is not None:
            raise self._error

    async def _serve(self, host: str) -> None:
        self._stop = asyncio.Event()
        servers = []
        try:
            for index, port in enumerate(self.ports):
                server = await websockets.serve(self._relay, host, port,
                                                subprotocols=SUBPROTOCOLS, max_size=None)
                servers.append(server)
                self.ports[index] = server.sockets[0].getsockname()[1]
        except OSError as exc:  # the port was taken since it was checked
            self._error = exc
        self._ready.set()
        if self._error is None:
            await self._stop.wait()
        for server in servers:
            server.close()
            await server.wait_closed()

    async def _relay(self, viewer: ServerConnection) -> None:
        try:
            async with websockets.connect(self._upstream, subprotocols=[SDK_SUBPROTOCOL],
                                          max_size=None, compression=None) as bridge:
                await viewer.send(await bridge.recv())  # serverInfo comes first
                status = self._status()
                if status is not None:
                    await viewer.send(status)
                pumps = [asyncio.create_task(self._pump(viewer, bridge)),
                         asyncio.create_task(self._pump(bridge, viewer))]
                await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for pump in pumps:
                    pump.cancel()
        except (OSError, websockets.WebSocketException) as exc:
            log.warning("viewer %s: %s", viewer.remote_address, exc)

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
