// Checks the bridge with the official client: npm install @foxglove/ws-protocol@0.8.0 ws, then
// node docs/ws_protocol_viewer.js ws://127.0.0.1:8765 actuators/elbow/state 3000
// prints the subprotocol, serverInfo name, channels, statuses and messages received.
// A viewer built on @foxglove/ws-protocol 0.8.0 (its FoxgloveClient over the `ws` package).
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");
const url = process.argv[2];
const topic = process.argv[3];
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const seen = { protocol: null, serverInfo: null, channels: [], statuses: [], messages: 0 };
client.on("open", () => { seen.protocol = ws.protocol; });
client.on("serverInfo", (info) => { seen.serverInfo = info.name; });
client.on("status", (s) => { seen.statuses.push(s); });
client.on("advertise", (channels) => {
  for (const c of channels) {
    seen.channels.push({ topic: c.topic, schemaName: c.schemaName, encoding: c.encoding });
    if (c.topic === topic) client.subscribe(c.id);
  }
});
client.on("message", () => { seen.messages += 1; });
client.on("error", (e) => { console.log(JSON.stringify({ error: String(e) })); process.exit(1); });
setTimeout(() => { console.log(JSON.stringify(seen)); process.exit(0); }, Number(process.argv[4] || 3000));
