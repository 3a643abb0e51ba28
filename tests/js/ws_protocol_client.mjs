// The official Foxglove ws-protocol client (what Lichtblick speaks), driven against a
// server: subscribe every channel for a while, fetch an asset, print what it saw as JSON.
// usage: node ws_protocol_client.mjs ws://HOST:PORT SECONDS ASSET_URI
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, seconds, assetUri] = process.argv.slice(2);
const decoder = new TextDecoder();
const seen = { subprotocol: null, serverInfo: null, channels: [], messages: {}, unparsable: 0,
               lastTf: null, asset: null, errors: [] };
const topics = new Map();

const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
ws.on("open", () => { seen.subprotocol = ws.protocol; });
client.on("error", (error) => seen.errors.push(String(error)));
client.on("serverInfo", (info) => {
  seen.serverInfo = info;
  if (info.capabilities.includes("assets")) client.fetchAsset(assetUri, 1);
});
client.on("advertise", (channels) => {
  for (const channel of channels) {
    seen.channels.push(channel);
    topics.set(client.subscribe(channel.id), channel.topic);
  }
});
client.on("message", ({ subscriptionId, data }) => {
  const topic = topics.get(subscriptionId);
  seen.messages[topic] = (seen.messages[topic] ?? 0) + 1;
  try {
    const message = JSON.parse(decoder.decode(data));
    if (topic === "/tf") seen.lastTf = message;
  } catch {
    seen.unparsable += 1;
  }
});
client.on("fetchAssetResponse", (response) => {
  seen.asset = response.status === 0
    ? { status: 0, bytes: response.data.byteLength, text: decoder.decode(response.data) }
    : { status: response.status, error: response.error };
});
setTimeout(() => {
  client.close();
  console.log(JSON.stringify(seen));
  process.exit(0);
}, Number(seconds) * 1000);
