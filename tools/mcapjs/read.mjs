// Foxglove's MCAP reader on a file: every message read through the summary index, CRCs checked;
// prints {messages, topics, attachments, metadata} as JSON. Exit 1 (an error) if it cannot read it.
// Foxglove's MCAP reader (@mcap/core McapIndexedReader): counts per topic, CRCs checked
import { McapIndexedReader } from "@mcap/core";
import * as zstd from "@foxglove/wasm-zstd";
import { open } from "node:fs/promises";
const fh = await open(process.argv[2], "r");
const size = (await fh.stat()).size;
const readable = { size: async () => BigInt(size), read: async (off, len) => {
  const buf = Buffer.alloc(Number(len)); await fh.read(buf, 0, Number(len), Number(off)); return new Uint8Array(buf.buffer, buf.byteOffset, buf.length); } };
await zstd.isLoaded;
const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers: { zstd: (d, n) => zstd.decompress(d, Number(n)) } });
const counts = {};
let n = 0;
for await (const m of reader.readMessages({ validateCrcs: true })) { const t = reader.channelsById.get(m.channelId).topic; counts[t] = (counts[t] || 0) + 1; n++; }
const att = []; for await (const a of reader.readAttachments()) att.push(a.name);
const meta = []; for await (const x of reader.readMetadata()) meta.push(x.name);
console.log(JSON.stringify({ messages: n, topics: Object.keys(counts).length, attachments: att.length, metadata: meta }));
await fh.close();
