// Foxglove's MCAP reader on a file: every message read through the summary index, CRCs checked;
// prints {messages, topics, attachments, metadata, start_ns, end_ns} as JSON. Exit 1 (an error)
// if it cannot read it. With --decode, every message is also decoded the way the Foxglove app
// decodes it (json: JSON.parse; protobuf: protobufjs from the channel's FileDescriptorSet, as
// Foxglove's mcap-support does) and per_topic gives {schema, encoding, count, decoded, errors,
// first_error, first} per topic (first: the first protobuf message as a plain object).
import { McapIndexedReader } from "@mcap/core";
import * as zstd from "@foxglove/wasm-zstd";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import { open } from "node:fs/promises";

const path = process.argv[2];
const decodeAll = process.argv.includes("--decode");
const fh = await open(path, "r");
const size = (await fh.stat()).size;
const readable = { size: async () => BigInt(size), read: async (off, len) => {
  const buf = Buffer.alloc(Number(len)); await fh.read(buf, 0, Number(len), Number(off)); return new Uint8Array(buf.buffer, buf.byteOffset, buf.length); } };
await zstd.isLoaded;
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: { zstd: (d, n) => zstd.decompress(d, Number(n)) } });

const text = new TextDecoder("utf-8", { fatal: true });
const decoders = new Map(); // channel id -> (bytes) => object, or an Error if the schema does not parse
function decoderFor(channel) {
  const schema = reader.schemasById.get(channel.schemaId);
  if (channel.messageEncoding === "json") return (data) => JSON.parse(text.decode(data));
  if (channel.messageEncoding === "protobuf") {
    const root = protobuf.Root.fromDescriptor(descriptor.FileDescriptorSet.decode(schema.data));
    const type = root.lookupType(schema.name);
    return (data) => type.toObject(type.decode(data), { longs: String, enums: String, defaults: true });
  }
  return null; // raw bytes (keys outside the contract): nothing to decode
}

const counts = {};
const perTopic = {};
let n = 0, start = null, end = null;
for await (const m of reader.readMessages({ validateCrcs: true })) {
  const ch = reader.channelsById.get(m.channelId);
  const t = ch.topic;
  counts[t] = (counts[t] || 0) + 1; n++;
  if (start === null || m.logTime < start) start = m.logTime;
  if (end === null || m.logTime > end) end = m.logTime;
  if (!decodeAll) continue;
  let entry = perTopic[t];
  if (!entry) {
    const schema = reader.schemasById.get(ch.schemaId);
    entry = perTopic[t] = { schema: schema ? schema.name : "", encoding: ch.messageEncoding, count: 0, decoded: 0, errors: 0, first_error: null, first: null };
  }
  entry.count++;
  if (!decoders.has(m.channelId)) {
    try { decoders.set(m.channelId, decoderFor(ch)); } catch (e) { decoders.set(m.channelId, e); }
  }
  const dec = decoders.get(m.channelId);
  if (dec === null) continue;
  try {
    if (dec instanceof Error) throw dec;
    const obj = dec(m.data);
    entry.decoded++;
    if (entry.first === null && ch.messageEncoding === "protobuf") entry.first = obj;
  } catch (e) {
    entry.errors++;
    if (entry.first_error === null) entry.first_error = String(e && e.message ? e.message : e);
  }
}
const att = []; for await (const a of reader.readAttachments()) att.push(a.name);
const meta = []; for await (const x of reader.readMetadata()) meta.push(x.name);
const out = { messages: n, topics: Object.keys(counts).length, attachments: att.length, metadata: meta,
  start_ns: start === null ? null : String(start), end_ns: end === null ? null : String(end) };
if (decodeAll) out.per_topic = perTopic;
console.log(JSON.stringify(out));
await fh.close();
