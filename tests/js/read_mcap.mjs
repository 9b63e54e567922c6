// Independent check of a gscompress log with the official TypeScript MCAP reader.
// Usage: node read_mcap.mjs FILE.mcap
// Prints one JSON object: profile, channels {topic: {schema, encoding, messages}},
// metadata names, and for /gaussians the point_stride, field names and point count of the last
// message (decoded with protobufjs from the schema stored in the file).
import { McapIndexedReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers } from "@mcap/support";
import protobufjs from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import { open } from "node:fs/promises";

const path = process.argv[2];
const handle = await open(path, "r");
const reader = await McapIndexedReader.Initialize({
  readable: new FileHandleReadable(handle),
  decompressHandlers: await loadDecompressHandlers(),
});
const channels = {};
for (const [id, channel] of reader.channelsById) {
  const schema = reader.schemasById.get(channel.schemaId);
  channels[channel.topic] = {
    schema: schema?.name ?? "",
    encoding: channel.messageEncoding,
    messages: Number(reader.statistics?.channelMessageCounts.get(id) ?? 0n),
  };
}
// Count messages by reading them all, independently of the statistics record.
const counted = {};
let last = null;
for await (const message of reader.readMessages()) {
  const topic = reader.channelsById.get(message.channelId).topic;
  counted[topic] = (counted[topic] ?? 0) + 1;
  if (topic === "/gaussians") last = message;
}
let gaussians = null;
if (last) {
  const channel = reader.channelsById.get(last.channelId);
  const schema = reader.schemasById.get(channel.schemaId);
  const root = protobufjs.Root.fromDescriptor(descriptor.FileDescriptorSet.decode(schema.data));
  const type = root.lookupType(schema.name);
  const cloud = type.toObject(type.decode(last.data), { longs: Number, defaults: true });
  gaussians = {
    point_stride: cloud.point_stride,
    fields: cloud.fields.map((f) => f.name),
    points: cloud.data.length / cloud.point_stride,
  };
}
const metadata = reader.metadataIndexes.map((index) => index.name);
console.log(JSON.stringify({ profile: reader.header.profile, channels, counted, metadata, gaussians }));
await handle.close();
