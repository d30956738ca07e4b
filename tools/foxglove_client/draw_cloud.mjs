// A Foxglove WebSocket client that draws one PointCloud2 of `galvoscan view` into a PNG.
//
// It speaks the protocol through Foxglove's own client library (@foxglove/ws-protocol),
// decodes the message with Foxglove's ROS 2 CDR reader (@foxglove/rosmsg2-serialization)
// from the `ros2msg` schema the server advertises, as Foxglove's 3D panel does, and draws
// the points seen along V0's z axis (the scanner's view), coloured by depth.
//
//   node draw_cloud.mjs [--url ws://127.0.0.1:8765] [--topic /points/scan]
//                       [--png cloud.png] [--timeout 30] [--min-points 1]
//
// The last line of its output is one JSON object: the topic, frame_id, the number of points
// (and how many are finite), their bounding box [m] and how many pixels of the picture they
// cover. Exit status 0 when a cloud of at least --min-points points was drawn, 1 otherwise.

import { writeFileSync } from 'node:fs';
import { deflateSync } from 'node:zlib';

import rosmsg from '@foxglove/rosmsg';
import serialization from '@foxglove/rosmsg2-serialization';
import wsProtocol from '@foxglove/ws-protocol';
import WebSocket from 'ws';

// CommonJS packages: their exports come through the default import
const { parse } = rosmsg;
const { MessageReader } = serialization;
const { FoxgloveClient } = wsProtocol;

const WIDTH = 640;
const HEIGHT = 480;
const FLOAT32 = 7; // sensor_msgs/PointField.FLOAT32

function options(argv) {
  const o = { url: 'ws://127.0.0.1:8765', topic: '/points/scan', png: '', timeout: 30,
    minPoints: 1 };
  for (let i = 0; i < argv.length; i += 2) {
    const [key, value] = [argv[i], argv[i + 1]];
    if (value === undefined) throw new Error(`${key} needs a value`);
    if (key === '--url') o.url = value;
    else if (key === '--topic') o.topic = value.startsWith('/') ? value : `/${value}`;
    else if (key === '--png') o.png = value;
    else if (key === '--timeout') o.timeout = Number(value);
    else if (key === '--min-points') o.minPoints = Number(value);
    else throw new Error(`unknown option ${key}`);
  }
  if (!(o.timeout > 0) || !(o.minPoints >= 0)) throw new Error('--timeout and --min-points must be positive numbers');
  return o;
}

// The x, y, z of every point of a decoded sensor_msgs/PointCloud2.
function xyz(cloud) {
  const field = (name) => {
    const f = cloud.fields.find((p) => p.name === name);
    if (!f || f.datatype !== FLOAT32) throw new Error(`the cloud has no float32 field ${name}`);
    return f.offset;
  };
  const [ox, oy, oz] = ['x', 'y', 'z'].map(field);
  const n = cloud.width * cloud.height;
  const view = new DataView(cloud.data.buffer, cloud.data.byteOffset, cloud.data.byteLength);
  const little = !cloud.is_bigendian;
  const out = new Float64Array(3 * n);
  for (let i = 0; i < n; i++) {
    const base = i * cloud.point_step;
    out[3 * i] = view.getFloat32(base + ox, little);
    out[3 * i + 1] = view.getFloat32(base + oy, little);
    out[3 * i + 2] = view.getFloat32(base + oz, little);
  }
  return out;
}

// RGBA picture of the points seen along z: x to the right, y down, depth as colour.
function draw(points) {
  const finite = [];
  for (let i = 0; i < points.length; i += 3) {
    if (Number.isFinite(points[i]) && Number.isFinite(points[i + 1]) && Number.isFinite(points[i + 2])) {
      finite.push(i);
    }
  }
  const lo = [Infinity, Infinity, Infinity];
  const hi = [-Infinity, -Infinity, -Infinity];
  for (const i of finite) {
    for (let k = 0; k < 3; k++) {
      lo[k] = Math.min(lo[k], points[i + k]);
      hi[k] = Math.max(hi[k], points[i + k]);
    }
  }
  const rgba = new Uint8Array(WIDTH * HEIGHT * 4);
  for (let p = 0; p < WIDTH * HEIGHT; p++) rgba.set([24, 24, 28, 255], 4 * p);
  const span = Math.max(hi[0] - lo[0], (hi[1] - lo[1]) * WIDTH / HEIGHT, 1e-9) * 1.1;
  const scale = WIDTH / span;
  const cx = (lo[0] + hi[0]) / 2;
  const cy = (lo[1] + hi[1]) / 2;
  const dz = Math.max(hi[2] - lo[2], 1e-9);
  let covered = 0;
  for (const i of finite) {
    const col = Math.round(WIDTH / 2 + (points[i] - cx) * scale);
    const row = Math.round(HEIGHT / 2 + (points[i + 1] - cy) * scale);
    if (col < 0 || col >= WIDTH || row < 0 || row >= HEIGHT) continue;
    const t = (points[i + 2] - lo[2]) / dz; // near: yellow, far: blue
    const p = 4 * (row * WIDTH + col);
    if (rgba[p] === 24 && rgba[p + 1] === 24) covered++;
    rgba.set([Math.round(255 * (1 - t)), Math.round(200 * (1 - t) + 80 * t), Math.round(255 * t), 255], p);
  }
  return { rgba, finite: finite.length, lo, hi, covered };
}

const CRC_TABLE = Array.from({ length: 256 }, (_, n) => {
  let c = n;
  for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  return c >>> 0;
});

function crc32(bytes) {
  let c = 0xffffffff;
  for (const b of bytes) c = CRC_TABLE[(c ^ b) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

function png(rgba) {
  const chunk = (type, body) => {
    const head = Buffer.alloc(8);
    head.writeUInt32BE(body.length, 0);
    head.write(type, 4, 'ascii');
    const crc = Buffer.alloc(4);
    crc.writeUInt32BE(crc32(Buffer.concat([head.subarray(4), body])), 0);
    return Buffer.concat([head, body, crc]);
  };
  const ihdr = Buffer.alloc(13);
  ihdr.writeUInt32BE(WIDTH, 0);
  ihdr.writeUInt32BE(HEIGHT, 4);
  ihdr.set([8, 6, 0, 0, 0], 8); // 8 bits per channel, RGBA
  const rows = Buffer.alloc(HEIGHT * (1 + 4 * WIDTH));
  for (let r = 0; r < HEIGHT; r++) {
    rows[r * (1 + 4 * WIDTH)] = 0; // no filter
    rows.set(rgba.subarray(4 * WIDTH * r, 4 * WIDTH * (r + 1)), r * (1 + 4 * WIDTH) + 1);
  }
  return Buffer.concat([Buffer.from([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]),
    chunk('IHDR', ihdr), chunk('IDAT', deflateSync(rows)), chunk('IEND', Buffer.alloc(0))]);
}

function main() {
  let o;
  try {
    o = options(process.argv.slice(2));
  } catch (err) {
    console.error(`draw_cloud: ${err.message}`);
    process.exit(2);
  }
  const client = new FoxgloveClient({ ws: new WebSocket(o.url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]) });
  const readers = new Map();
  let seen = 0;
  const timer = setTimeout(() => {
    console.error(`draw_cloud: no cloud of at least ${o.minPoints} points on ${o.topic} within ${o.timeout} s (${seen} messages seen)`);
    client.close();
    process.exit(1);
  }, o.timeout * 1000);
  client.on('error', (err) => console.error(`draw_cloud: ${err.message ?? err}`));
  client.on('advertise', (channels) => {
    for (const ch of channels) {
      if (ch.topic !== o.topic) continue;
      if (ch.encoding !== 'cdr' || ch.schemaEncoding !== 'ros2msg') {
        console.error(`draw_cloud: ${ch.topic} is ${ch.encoding}/${ch.schemaEncoding}, not cdr/ros2msg`);
        process.exit(1);
      }
      readers.set(client.subscribe(ch.id), { channel: ch, reader: new MessageReader(parse(ch.schema, { ros2: true })) });
    }
  });
  client.on('message', ({ subscriptionId, data }) => {
    const sub = readers.get(subscriptionId);
    if (!sub) return;
    seen++;
    const cloud = sub.reader.readMessage(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    const points = xyz(cloud);
    if (points.length / 3 < o.minPoints) return;
    const pic = draw(points);
    if (o.png) writeFileSync(o.png, png(pic.rgba));
    clearTimeout(timer);
    console.log(JSON.stringify({
      topic: sub.channel.topic, schema: sub.channel.schemaName, frame_id: cloud.header.frame_id,
      points: points.length / 3, finite: pic.finite, bbox_min_m: pic.lo, bbox_max_m: pic.hi,
      pixels_drawn: pic.covered, png: o.png || null,
    }));
    client.close();
    process.exit(0);
  });
}

main();
