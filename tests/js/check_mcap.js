// Reads an MCAP file with @mcap/core, twice: as a stream (every record, CRCs checked) and through
// its summary index (readMessages). Validates every JSON message of a channel whose schema is
// foxglove.* against the published @foxglove/schemas JSON schema of that name, and against the
// schema stored in the file. Prints one JSON report on stdout; exits 1 when anything is wrong.
"use strict";
const fs = require("fs");
const { McapStreamReader, McapIndexedReader } = require("@mcap/core");
const foxglove = require("@foxglove/schemas/jsonschema");
const Ajv = require("ajv");
const fzstd = require("fzstd");

const decompressHandlers = {
  zstd: (buffer, size) => fzstd.decompress(buffer, new Uint8Array(Number(size))),
};

function validatorFor(ajv, cache, key, schema) {
  if (!cache.has(key)) cache.set(key, ajv.compile(schema));
  return cache.get(key);
}

async function main(path) {
  const bytes = new Uint8Array(fs.readFileSync(path));
  const report = { file: path, errors: [], topics: {}, schemas: {}, indexed_messages: 0 };
  const ajv = new Ajv({ strict: false, allErrors: false });
  const official = new Map();
  const stored = new Map();

  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(bytes);
  const schemas = new Map();
  const channels = new Map();
  let record;
  let sawFooter = false;
  while ((record = stream.nextRecord())) {
    if (record.type === "Schema") schemas.set(record.id, record);
    else if (record.type === "Channel") channels.set(record.id, record);
    else if (record.type === "Footer") sawFooter = true;
    else if (record.type === "Message") {
      const channel = channels.get(record.channelId);
      const topic = channel.topic;
      const entry = (report.topics[topic] ??= {
        count: 0,
        message_encoding: channel.messageEncoding,
        schema: channel.schemaId ? schemas.get(channel.schemaId).name : "",
        first_log_time: record.logTime.toString(),
        last_log_time: "",
      });
      entry.count += 1;
      entry.last_log_time = record.logTime.toString();
      if (!entry.schema.startsWith("foxglove.")) continue;
      const name = entry.schema.slice("foxglove.".length);
      const schemaRecord = schemas.get(channel.schemaId);
      report.schemas[entry.schema] = schemaRecord.encoding;
      if (!(name in foxglove)) {
        report.errors.push(`${topic}: no published Foxglove schema ${entry.schema}`);
        continue;
      }
      let message;
      try {
        message = JSON.parse(new TextDecoder().decode(record.data));
      } catch (e) {
        report.errors.push(`${topic}: message is not JSON (${e.message})`);
        continue;
      }
      const checks = [
        ["published", validatorFor(ajv, official, name, foxglove[name])],
        [
          "stored",
          validatorFor(
            ajv,
            stored,
            channel.schemaId,
            JSON.parse(new TextDecoder().decode(schemaRecord.data)),
          ),
        ],
      ];
      for (const [which, validate] of checks) {
        if (!validate(message) && report.errors.length < 20) {
          report.errors.push(
            `${topic} @${record.logTime}: not a valid ${entry.schema} (${which} schema): ` +
              ajv.errorsText(validate.errors),
          );
        }
      }
    }
  }
  if (!sawFooter || !stream.done()) report.errors.push("the stream did not end with a footer");

  const readable = {
    size: async () => BigInt(bytes.byteLength),
    read: async (offset, size) => bytes.subarray(Number(offset), Number(offset + size)),
  };
  const indexed = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  for await (const _ of indexed.readMessages({ validateCrcs: true })) report.indexed_messages += 1;
  report.statistics_messages = indexed.statistics ? Number(indexed.statistics.messageCount) : -1;
  process.stdout.write(JSON.stringify(report) + "\n");
  return report.errors.length === 0 ? 0 : 1;
}

main(process.argv[2]).then(
  (code) => process.exit(code),
  (err) => {
    process.stdout.write(JSON.stringify({ file: process.argv[2], errors: [String(err)] }) + "\n");
    process.exit(1);
  },
);
