// The reference Foxglove WebSocket client (@foxglove/ws-protocol) against a live server.
//
// Usage: node client.js URL MIN_MESSAGES TIMEOUT_S KIND...
// Connects with the subprotocol foxglove.sdk.v1 (foxglove-sdk 0.30 refuses the client's
// default foxglove.websocket.v1), subscribes to every advertised channel whose topic is
// glider/{id}/{KIND}... or, for a KIND outside glider/ (mavlink/raw, mavlink/json/in),
// {KIND}..., validates each message against the JSON Schema the server advertised for its
// channel (ajv, draft 2020-12) or, on a schemaless mavlink2 channel, as one whole MAVLink 2
// frame (magic, length, signature flag), and prints one JSON summary when every KIND has
// MIN_MESSAGES valid messages or TIMEOUT_S has passed.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { WebSocket } = require("ws");
const Ajv2020 = require("ajv/dist/2020").default;

const [url, minArg, timeoutArg, ...kinds] = process.argv.slice(2);
const minMessages = Number(minArg);
const timeoutMs = Number(timeoutArg) * 1000;
const SUBPROTOCOL = "foxglove.sdk.v1";

const ajv = new Ajv2020({ strict: false, allErrors: true });
const summary = {
  subprotocol: null,
  server: null,
  advertised: [],
  subscribed: [],
  kinds: Object.fromEntries(kinds.map((k) => [k, { messages: 0, valid: 0, invalid: 0 }])),
  errors: [],
  complete: false,
};
const bySubscription = new Map(); // subscription id -> {topic, kind, validate}
const validators = new Map(); // schema text -> compiled validator (channels share schemas)

function kindOf(topic) {
  const parts = topic.split("/");
  const rest = parts[0] === "glider" && parts.length >= 3 ? parts.slice(2).join("/") : topic;
  return kinds.find((k) => rest === k || rest.startsWith(k + "/")) ?? null;
}

// A MAVLink 2 frame, whole: magic 0xFD, header 10 bytes, payload, CRC 2, signature 13 when
// the incompatibility flag 0x01 is set.
function validMavlink2(bytes) {
  if (bytes.length < 12 || bytes[0] !== 0xfd) return false;
  const signed = (bytes[2] & 0x01) !== 0;
  return bytes.length === 10 + bytes[1] + 2 + (signed ? 13 : 0);
}

function done() {
  return kinds.every((k) => summary.kinds[k].valid >= minMessages);
}

let finished = false;
function finish(client, code) {
  if (finished) return;
  finished = true;
  summary.complete = done();
  process.stdout.write(JSON.stringify(summary) + "\n");
  try {
    client.close();
  } catch (_) {
    // already closed
  }
  process.exit(code);
}

const ws = new WebSocket(url, [SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const timer = setTimeout(() => finish(client, 0), timeoutMs);
const decoder = new TextDecoder();

client.on("open", () => {
  summary.subprotocol = ws.protocol;
});
client.on("serverInfo", (info) => {
  summary.server = { name: info.name, capabilities: info.capabilities };
});
client.on("error", (error) => {
  summary.errors.push(`client error: ${error && error.message ? error.message : error}`);
});
client.on("close", (event) => {
  summary.errors.push(`closed: ${event && event.code}`);
  clearTimeout(timer);
  finish(client, 1);
});
client.on("advertise", (channels) => {
  for (const channel of channels) {
    summary.advertised.push({
      topic: channel.topic,
      encoding: channel.encoding,
      schemaName: channel.schemaName,
      schemaEncoding: channel.schemaEncoding,
      schemaLength: (channel.schema ?? "").length,
    });
    const kind = kindOf(channel.topic);
    if (kind === null) continue;
    if (channel.encoding === "mavlink2") {
      const id = client.subscribe(channel.id);
      bySubscription.set(id, { topic: channel.topic, kind, raw: true });
      summary.subscribed.push(channel.topic);
      continue;
    }
    let validate = validators.get(channel.schema);
    try {
      if (validate === undefined) {
        validate = ajv.compile(JSON.parse(channel.schema));
        validators.set(channel.schema, validate);
      }
    } catch (error) {
      summary.errors.push(`${channel.topic}: schema does not compile: ${error.message}`);
      continue;
    }
    const id = client.subscribe(channel.id);
    bySubscription.set(id, { topic: channel.topic, kind, validate });
    summary.subscribed.push(channel.topic);
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const sub = bySubscription.get(subscriptionId);
  if (sub === undefined) return;
  const counts = summary.kinds[sub.kind];
  counts.messages += 1;
  if (sub.raw) {
    const bytes = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
    if (validMavlink2(bytes)) {
      counts.valid += 1;
    } else {
      counts.invalid += 1;
      if (summary.errors.length < 20) summary.errors.push(`${sub.topic}: not one MAVLink 2 frame`);
    }
    if (done()) {
      clearTimeout(timer);
      finish(client, 0);
    }
    return;
  }
  let payload;
  try {
    payload = JSON.parse(decoder.decode(data));
  } catch (error) {
    counts.invalid += 1;
    summary.errors.push(`${sub.topic}: not JSON: ${error.message}`);
    return;
  }
  if (sub.validate(payload)) {
    counts.valid += 1;
  } else {
    counts.invalid += 1;
    if (summary.errors.length < 20) {
      summary.errors.push(`${sub.topic}: ${ajv.errorsText(sub.validate.errors)}`);
    }
  }
  if (done()) {
    clearTimeout(timer);
    finish(client, 0);
  }
});
