// A Foxglove WebSocket client as Foxglove Studio was before the SDK: ws-protocol's own
// FoxgloveClient, offering only the subprotocol it supports ("foxglove.websocket.v1").
//   node tools/mcapjs/wsclient.mjs URL TIMEOUT_S MIN_MESSAGES TOPIC...
// Connects, subscribes to each TOPIC once advertised, and prints one JSON line: the subprotocol
// chosen, the server's name, every advertised channel, and per TOPIC the messages received
// (log time in ns as a string, payload in base64) once each has MIN_MESSAGES or at TIMEOUT_S.
import wsProtocol from "@foxglove/ws-protocol"; // CommonJS: its default export
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, timeoutS, minMessages, ...topics] = process.argv.slice(2);
const want = new Set(topics);
const out = { subprotocol: null, serverName: null, channels: [], messages: {}, errors: [] };
const bySub = new Map();
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });

let finished = false;
function done() {
  if (finished) return;
  finished = true;
  out.subprotocol = ws.protocol || null;
  client.close();
  // exit once the line is out: a pipe takes a large one in parts
  process.stdout.write(JSON.stringify(out) + "\n", () => process.exit(0));
}

const timer = setTimeout(done, Number(timeoutS) * 1000);
client.on("error", (err) => out.errors.push(String(err?.message ?? err)));
client.on("serverInfo", (info) => {
  out.serverName = info.name;
});
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels.push({ id: ch.id, topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName, schema: ch.schema });
    if (want.has(ch.topic)) {
      bySub.set(client.subscribe(ch.id), ch.topic);
    }
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = bySub.get(subscriptionId);
  if (topic === undefined) return;
  const list = (out.messages[topic] ??= []);
  list.push([String(timestamp), Buffer.from(data.buffer, data.byteOffset, data.byteLength).toString("base64")]);
  if ([...want].every((t) => (out.messages[t]?.length ?? 0) >= Number(minMessages))) {
    clearTimeout(timer);
    done();
  }
});
client.on("close", () => {
  clearTimeout(timer);
  done();
});
