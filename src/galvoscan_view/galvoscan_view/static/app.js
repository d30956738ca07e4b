// The galvoscan view page: the live cloud in 3D, the camera image with its stripe, the scan
// progress, the galvo state, the diagnostics and message counts, and the calibration view
// (instruction, last view's detections, standard errors, coverage, operator buttons), all
// read from the API of galvoscan_view/web.py (same origin; nothing else is loaded).
//
// Coordinates are the cloud's frame (v0: optical, x right, y down, z away from the scanner),
// in metres; the 3D view keeps them as they are and puts -y up on the screen.

import * as THREE from './vendor/three.module.js';
import { OrbitControls } from './vendor/OrbitControls.js';

const POLL_GAP_MS = 100;        // at most ten state summaries a second
const CLOUD_GAP_MS = 250;       // at most four cloud downloads a second
const LONG_POLL_S = 10;
const $ = (id) => document.getElementById(id);
const fmt = new Intl.NumberFormat('en-US');
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

// ---- framed binary messages (web.framed) ------------------------------------------------------

function unframe(buffer) {
  const n = new DataView(buffer).getUint32(0, true);
  const meta = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, n)));
  let offset = 4 + n + ((4 - ((4 + n) % 4)) % 4);
  const payloads = meta.payload_bytes.map((len) => {
    const slice = buffer.slice(offset, offset + len);
    offset += len;
    return slice;
  });
  return { meta, payloads };
}

async function fetchFramed(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: ${response.status} ${await response.text()}`);
  return unframe(await response.arrayBuffer());
}

// ---- colour map (viridis, 9 stops) -----------------------------------------------------------

const VIRIDIS = [
  [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530],
  [0.207, 0.372, 0.553], [0.164, 0.471, 0.558], [0.128, 0.567, 0.551],
  [0.135, 0.659, 0.518], [0.267, 0.749, 0.441], [0.478, 0.821, 0.318],
  [0.741, 0.873, 0.150], [0.993, 0.906, 0.144],
];

function viridis(t, out, i) {
  const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
  const k = Math.min(Math.floor(x), VIRIDIS.length - 2);
  const f = x - k;
  const a = VIRIDIS[k], b = VIRIDIS[k + 1];
  for (let c = 0; c < 3; c++) out[i + c] = a[c] + (b[c] - a[c]) * f;
}

// The renderer writes sRGB and takes vertex colours as linear: a table of linear values.
const LUT_SIZE = 256;
const LUT = new Float32Array(3 * LUT_SIZE);
for (let j = 0; j < LUT_SIZE; j++) {
  viridis(j / (LUT_SIZE - 1), LUT, 3 * j);
  for (let c = 0; c < 3; c++) {
    const v = LUT[3 * j + c];
    LUT[3 * j + c] = v <= 0.04045 ? v / 12.92 : Math.pow((v + 0.055) / 1.055, 2.4);
  }
}

function colourOf(t, out, i) {
  const j = 3 * Math.round(Math.min(Math.max(t, 0), 1) * (LUT_SIZE - 1)) || 0;
  out[i] = LUT[j];
  out[i + 1] = LUT[j + 1];
  out[i + 2] = LUT[j + 2];
}

function percentiles(values, ps) {
  const step = Math.max(1, Math.floor(values.length / 50000));
  const sample = [];
  for (let i = 0; i < values.length; i += step) if (Number.isFinite(values[i])) sample.push(values[i]);
  sample.sort((a, b) => a - b);
  return ps.map((p) => sample.length ? sample[Math.min(sample.length - 1, Math.floor(p * sample.length))] : 0);
}

// ---- the 3D view -----------------------------------------------------------------------------

const view = {
  renderer: null, scene: null, camera: null, controls: null, points: null,
  xyz: null, error: null, fitted: null, userMoved: false, pending: false,
};

function initView() {
  const host = $('view3d');
  view.renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  view.renderer.setPixelRatio(window.devicePixelRatio || 1);
  host.appendChild(view.renderer.domElement);
  view.scene = new THREE.Scene();
  view.scene.background = new THREE.Color(0x23272e);
  view.camera = new THREE.PerspectiveCamera(45, 1, 0.001, 100);
  view.camera.up.set(0, -1, 0);              // v0 is optical: y points down
  view.camera.position.set(0, 0, -0.5);
  view.controls = new OrbitControls(view.camera, view.renderer.domElement);
  view.controls.addEventListener('change', requestRender);
  view.controls.addEventListener('start', () => { view.userMoved = true; });
  const geometry = new THREE.BufferGeometry();
  const material = new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true });
  view.points = new THREE.Points(geometry, material);
  view.points.frustumCulled = false;
  view.scene.add(view.points);
  view.axes = new THREE.AxesHelper(0.05);    // v0's axes at its origin (the scanner), 50 mm
  view.scene.add(view.axes);
  new ResizeObserver(resize).observe(host);
  resize();
}

function resize() {
  const host = $('view3d');
  const w = Math.max(1, host.clientWidth), h = Math.max(1, host.clientHeight);
  view.renderer.setSize(w, h, false);
  view.camera.aspect = w / h;
  view.camera.updateProjectionMatrix();
  requestRender();
}

function requestRender() {
  if (view.pending) return;
  view.pending = true;
  requestAnimationFrame(() => {
    view.pending = false;
    view.renderer.render(view.scene, view.camera);
  });
}

// Looks at the cloud from the scanner's side (-z), a little from above and the right, so
// that relief shows, from the nearest distance at which all 8 corners of its bounding box
// are in view (with a margin for the overlays).
function fitView(bounds) {
  const [lo, hi] = bounds;
  const centre = new THREE.Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
  const back = new THREE.Vector3(0.45, -0.55, -1).normalize();   // from the centre to the eye
  const right = new THREE.Vector3().crossVectors(view.camera.up, back).normalize();
  const up = new THREE.Vector3().crossVectors(back, right);
  const tanV = Math.tan(THREE.MathUtils.degToRad(view.camera.fov) / 2) / 1.15;
  const tanH = tanV * view.camera.aspect;
  let distance = 1e-3;
  for (let k = 0; k < 8; k++) {
    const corner = new THREE.Vector3(k & 1 ? hi[0] : lo[0], k & 2 ? hi[1] : lo[1], k & 4 ? hi[2] : lo[2]).sub(centre);
    const toward = corner.dot(back);
    distance = Math.max(distance, toward + Math.abs(corner.dot(right)) / tanH,
      toward + Math.abs(corner.dot(up)) / tanV);
  }
  view.camera.position.copy(centre).addScaledVector(back, distance);
  view.camera.near = Math.max(1e-4, distance / 100);
  view.camera.far = distance * 100;
  view.camera.updateProjectionMatrix();
  view.controls.target.copy(centre);
  view.controls.update();
  view.fitted = bounds;
  view.userMoved = false;
  requestRender();
}

// A new cloud is refitted while the user has not moved the view and it outgrew the last fit.
function outgrown(bounds) {
  if (!view.fitted) return true;
  const [lo, hi] = view.fitted;
  for (let k = 0; k < 3; k++) {
    const margin = 0.1 * Math.max(hi[k] - lo[k], 0.01);
    if (bounds[0][k] < lo[k] - margin || bounds[1][k] > hi[k] + margin) return true;
  }
  return false;
}

function colourValues(mode) {
  const xyz = view.xyz, n = xyz.length / 3;
  const values = new Float32Array(n);
  if (mode === 'error' && view.error) {
    for (let i = 0; i < n; i++) values[i] = view.error[i] * 1000;
    return { values, title: 'distance to the reference [mm]', zeroBased: true };
  }
  if (mode === 'x' || mode === 'y') {
    const k = mode === 'x' ? 0 : 1;
    for (let i = 0; i < n; i++) values[i] = xyz[3 * i + k] * 1000;
    return { values, title: `${mode} in ${state.frame || 'v0'} [mm]`, zeroBased: false };
  }
  // height toward the scanner: how far a point stands in front of the far surface (-z)
  const z = new Float32Array(n);
  for (let i = 0; i < n; i++) z[i] = xyz[3 * i + 2];
  const [far] = percentiles(z, [0.995]);
  for (let i = 0; i < n; i++) values[i] = (far - z[i]) * 1000;
  return { values, title: 'height toward the scanner (−z), above the far surface [mm]', zeroBased: false };
}

function recolour() {
  if (!view.xyz) return;
  const mode = $('colour-mode').value;
  const { values, title, zeroBased } = colourValues(mode);
  let [lo, hi] = percentiles(values, [0.01, 0.99]);
  if (zeroBased) lo = 0;
  if (!(hi > lo)) hi = lo + 1e-3;
  const colours = new Float32Array(values.length * 3);
  for (let i = 0; i < values.length; i++) colourOf((values[i] - lo) / (hi - lo), colours, 3 * i);
  view.points.geometry.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  drawLegend(title, lo, hi);
  requestRender();
}

function drawLegend(title, lo, hi) {
  const bar = $('legend-bar'), ctx = bar.getContext('2d');
  const img = ctx.createImageData(bar.width, 1), rgb = new Float32Array(3);
  for (let i = 0; i < bar.width; i++) {
    viridis(i / (bar.width - 1), rgb, 0);
    img.data.set([rgb[0] * 255, rgb[1] * 255, rgb[2] * 255, 255], 4 * i);
  }
  ctx.putImageData(img, 0, 0);
  const digits = hi - lo < 1 ? 3 : hi - lo < 10 ? 2 : 1;
  $('legend-title').textContent = title;
  $('legend-lo').textContent = lo.toFixed(digits);
  $('legend-mid').textContent = ((lo + hi) / 2).toFixed(digits);
  $('legend-hi').textContent = hi.toFixed(digits);
  $('legend').hidden = false;
}

function showCloud(meta, payloads) {
  const n = meta.points;
  view.xyz = new Float32Array(payloads[0] || new ArrayBuffer(0), 0, 3 * n);
  view.error = meta.error ? new Float32Array(payloads[1], 0, n) : null;
  const geometry = view.points.geometry;
  geometry.setAttribute('position', new THREE.BufferAttribute(view.xyz, 3));
  geometry.setDrawRange(0, n);
  geometry.computeBoundingSphere();
  const count = $('point-count');
  count.textContent = fmt.format(meta.points_total);
  count.dataset.total = String(meta.points_total);
  count.dataset.drawn = String(n);
  count.dataset.version = String(meta.version);
  $('point-detail').textContent = n < meta.points_total ? `(${fmt.format(n)} drawn)` : '';
  $('cloud-empty').hidden = n > 0;
  state.lastBounds = meta.bounds;
  if (n > 0 && meta.bounds && !view.userMoved && outgrown(meta.bounds)) fitView(meta.bounds);
  const size = meta.bounds ? meta.bounds[1].map((h, k) => ((h - meta.bounds[0][k]) * 1000).toFixed(0)) : null;
  $('axes-note').textContent = size ? `${meta.frame_id}: ${size.join(' × ')} mm (x × y × z); axes at the origin: x red, y green, z blue` : '';
  recolour();
}

// ---- the camera image ------------------------------------------------------------------------

async function showImage(meta, payloads) {
  const canvas = $('image');
  if (meta.seq === null) return;
  const bitmap = await createImageBitmap(new Blob([payloads[1]], { type: 'image/png' }));
  if (canvas.width !== meta.width || canvas.height !== meta.height) {
    canvas.width = meta.width;
    canvas.height = meta.height;
  }
  const ctx = canvas.getContext('2d');
  ctx.drawImage(bitmap, 0, 0);
  bitmap.close();
  const uv = new Float32Array(payloads[0], 0, 2 * meta.stripe_points);
  ctx.fillStyle = '#ff2020';
  const r = Math.max(1, meta.width / 400);  // a visible dot when the canvas is scaled down
  for (let i = 0; i < meta.stripe_points; i++) ctx.fillRect(uv[2 * i] - r, uv[2 * i + 1] - r, 2 * r, 2 * r);
  canvas.dataset.seq = String(meta.seq);
  canvas.dataset.stripePoints = String(meta.stripe_points);
  $('image-info').textContent = `${meta.width}×${meta.height}, ${meta.stripe_points} stripe centres`;
  $('image-info').title = `stamp ${meta.stamp.toFixed(6)} s`;
}

// ---- panels from /api/state ------------------------------------------------------------------

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = text;
  if (cls) e.className = cls;
  return e;
}

function fillTable(table, rows) {
  table.replaceChildren(...rows.map(([k, v]) => {
    const tr = el('tr');
    tr.append(el('td', k), el('td', v));
    return tr;
  }));
}

function levelClass(level) {
  return { OK: 'ok', WARN: 'warn', ERROR: 'error' }[level] || 'stale';
}

function showProgress(p) {
  const badge = $('scan-state');
  if (!p || p.frames_total === undefined) return;
  const done = p.frames_done || 0, total = p.frames_total || 0;
  $('progress-bar').max = Math.max(total, 1);
  $('progress-bar').value = done;
  badge.textContent = p.state || 'unknown';
  badge.className = `badge ${p.state === 'running' ? 'ok' : 'stale'}`;
  const pct = total ? ` (${(100 * done / total).toFixed(0)} %)` : '';
  $('progress-text').textContent = `${fmt.format(done)} / ${fmt.format(total)} frames${pct}, ${fmt.format(p.frames_dropped || 0)} dropped`;
  $('progress-text').dataset.done = String(done);
  $('progress-text').dataset.total = String(total);
}

function showGalvo(g) {
  if (!g) return;
  const names = ['U1 pan (G1)', 'U1 tilt (G1)', 'U2 pan (G2)', 'U2 tilt (G2)'];
  fillTable($('galvo'), [
    ...g.voltages.map((v, i) => [names[i], `${v.toFixed(4)} V`]),
    ['laser', g.laser_on ? 'on' : 'off'], ['status', String(g.status)], ['seq', fmt.format(g.seq)],
  ]);
}

function showDiagnostics(diagnostics) {
  const names = Object.keys(diagnostics).sort();
  if (!names.length) return;
  $('diagnostics').replaceChildren(...names.map((name) => {
    const { level, message, ...values } = diagnostics[name];
    const box = el('div', undefined, 'status');
    const head = el('div', undefined, 'status-head');
    head.append(el('span', level, `badge ${levelClass(level)}`), el('span', name, 'status-name'));
    const table = el('table', undefined, 'values');
    fillTable(table, Object.keys(values).sort().map((k) => [k, values[k]]));
    box.append(head, el('div', message || '', 'status-message dim'), table);
    return box;
  }));
}

const state = {
  frame: '', summary: null, cloudHave: -1, cloudKey: '', imageHave: -1, busy: {}, lastBounds: null,
};

function showSummary(s) {
  state.summary = s;
  showCalibration(s.calibration || {});
  showProgress(s.progress);
  showGalvo(s.galvo);
  showDiagnostics(s.diagnostics || {});
  const topics = Object.keys(s.counts || {}).sort();
  fillTable($('counts'), topics.length ? topics.map((t) => [t, fmt.format(s.counts[t])]) : [['none yet', '']]);
  const errorOption = $('colour-mode').querySelector('option[value=error]');
  errorOption.disabled = !s.reference;
  if (!s.reference && $('colour-mode').value === 'error') {
    $('colour-mode').value = 'height';
    recolour();
  }
  $('reference-info').textContent = s.reference ? `${fmt.format(s.reference.points)} points` : 'none';
  if (s.cloud) state.frame = s.cloud.frame_id;
  $('header-info').textContent = s.cloud ? `frame ${s.cloud.frame_id}, state version ${s.version}` : `state version ${s.version}`;
}

function setConnection(ok, text) {
  const badge = $('connection');
  badge.textContent = text;
  badge.className = `badge ${ok ? 'ok' : 'error'}`;
}

// ---- the loops -------------------------------------------------------------------------------

function cloudUrl() {
  const wantError = $('colour-mode').value === 'error' ? 1 : 0;
  return `api/cloud?max=${$('max-points').value}&error=${wantError}`;
}

// Downloads the cloud while the state holds a newer one than shown (or the request changed).
async function cloudLoop() {
  if (state.busy.cloud) return;
  state.busy.cloud = true;
  try {
    for (;;) {
      const s = state.summary;
      if (!s || !s.cloud) break;
      const url = cloudUrl(), key = `${url}|${s.versions.reference}`;
      if (s.versions.cloud <= state.cloudHave && key === state.cloudKey) break;
      const started = performance.now();
      const { meta, payloads } = await fetchFramed(url);
      state.cloudHave = meta.version;
      state.cloudKey = key;
      showCloud(meta, payloads);
      await sleep(Math.max(0, CLOUD_GAP_MS - (performance.now() - started)));
    }
  } catch (err) {
    console.warn('cloud', err);
  } finally {
    state.busy.cloud = false;
  }
}

async function imageLoop() {
  if (state.busy.image) return;
  state.busy.image = true;
  try {
    while (state.summary.image && state.summary.versions.image > state.imageHave) {
      const { meta, payloads } = await fetchFramed('api/image');
      state.imageHave = meta.version;
      await showImage(meta, payloads);
    }
  } catch (err) {
    console.warn('image', err);
  } finally {
    state.busy.image = false;
  }
}

async function pollLoop() {
  let since = -1;
  for (;;) {
    try {
      const response = await fetch(`api/state?since=${since}&timeout=${LONG_POLL_S}`);
      if (!response.ok) throw new Error(`${response.status} ${await response.text()}`);
      const s = await response.json();
      since = s.version;
      setConnection(true, 'live');
      showSummary(s);
      cloudLoop();
      imageLoop();
      calibrationViewLoop();
      await sleep(POLL_GAP_MS);
    } catch (err) {
      setConnection(false, 'disconnected: retrying');
      console.warn('state', err);
      await sleep(1000);
    }
  }
}

// ---- controls --------------------------------------------------------------------------------

// POST sets the reference (from the current cloud, or a file as the body), DELETE clears it.
async function setReference(method, url, body) {
  const response = await fetch(url, { method, body });
  const text = await response.text();
  $('reference-info').textContent = response.ok ? 'updating…' : `refused: ${text.trim()}`;
  $('reference-info').className = response.ok ? 'dim' : 'error';
  if (response.ok && method === 'POST') {
    $('colour-mode').querySelector('option[value=error]').disabled = false;
    $('colour-mode').value = 'error';
  }
  state.cloudKey = '';
  if (state.summary) cloudLoop();
}

function initControls() {
  $('fit').addEventListener('click', () => { if (state.lastBounds) fitView(state.lastBounds); });
  $('colour-mode').addEventListener('change', () => { state.cloudKey = ''; recolour(); if (state.summary) cloudLoop(); });
  $('max-points').addEventListener('change', () => { state.cloudKey = ''; if (state.summary) cloudLoop(); });
  $('point-size').addEventListener('input', (e) => { view.points.material.size = Number(e.target.value); requestRender(); });
  $('reference-take').addEventListener('click', () => setReference('POST', 'api/reference?from=cloud'));
  $('reference-clear').addEventListener('click', () => setReference('DELETE', 'api/reference'));
  $('reference-file').addEventListener('change', (e) => {
    const file = e.target.files[0];
    if (file) setReference('POST', `api/reference?name=${encodeURIComponent(file.name)}`, file);
    e.target.value = '';
  });
}

// ---- the calibration view -------------------------------------------------------------------

const MARK_KEPT = '#3fb950', MARK_REJECTED = '#f85149';
const deg = (rad) => rad * 180 / Math.PI;
const mm = (m) => m * 1000;
const f1 = (x) => (Math.abs(x) < 0.05 ? 0 : x).toFixed(1);
const calib = { viewHave: -1, shown: null };

// SI value -> shown value and unit: lengths in mm or um, angles in mrad or urad, the rest as is.
function shownUnit(unit, values) {
  const top = Math.max(0, ...values.filter((v) => v !== null && Number.isFinite(v)).map(Math.abs));
  if (unit === 'm') return top && top < 1e-3 ? [1e6, 'µm'] : [1e3, 'mm'];
  if (unit === 'rad') return top && top < 1e-3 ? [1e6, 'µrad'] : [1e3, 'mrad'];
  return [1, unit];
}

function precise(x) {
  if (x === null || x === undefined || !Number.isFinite(x)) return '—';
  const a = Math.abs(x);
  return a >= 100 ? x.toFixed(0) : a >= 10 ? x.toFixed(1) : a >= 1 ? x.toFixed(2) : x.toPrecision(2);
}

function setTab(tab) {
  const calibration = tab === 'calibration';
  $('cloud-panel').hidden = calibration;
  $('calib-panel').hidden = !calibration;
  $('tab-scan').setAttribute('aria-selected', String(!calibration));
  $('tab-calibration').setAttribute('aria-selected', String(calibration));
  if (!calibration) resize();
}

function showInstruction(ins) {
  if (!ins) return;
  calib.shown = ins;
  const badge = $('instr-state');
  badge.textContent = ins.state || 'unknown';
  badge.className = `badge ${{ place: 'warn', move: 'error', search: 'ok', capture: 'ok', done: 'ok', failed: 'error' }[ins.state] || 'stale'}`;
  badge.dataset.sequence = String(ins.sequence);
  $('instr-stage').textContent = ins.stage || '';
  $('instr-placement').textContent = ins.stage ? `placement ${ins.placement + 1} of ${ins.placements_planned}` : '';
  $('instr-text').textContent = ins.text || '';
  $('instr-direction').textContent = ins.state === 'move' && ins.direction ? `→ ${ins.direction}` : '';
  $('calib-tab-state').textContent = ins.stage ? `${ins.stage}: ${ins.state}` : '';
  const rows = [];
  if (ins.target) {
    const spec = ins.target_spec;
    rows.push(['target', `${ins.target}${ins.by_robot ? ' (by the robot)' : ''}`]);
    if (spec) rows.push(['target size', spec.replace(/[{}]/g, '')]);
  }
  if (ins.stage && !ins.by_robot && ins.state !== 'done' && ins.state !== 'failed') {
    const [x, y, z] = ins.centre.map(mm), [ex, ey, ez] = ins.extents.map(mm);
    rows.push([`region centre (${ins.frame_id || 'v0'})`, `x ${f1(x)}, y ${f1(y)} mm`]);
    rows.push(['depth z', `${f1(z)} mm ± ${f1(ez)} mm`]);
    rows.push(['region extents', `± ${f1(ex)} mm (x), ± ${f1(ey)} mm (y)`]);
    rows.push(['tilt to the scanner', `${deg(ins.tilt).toFixed(1)}° ± ${deg(ins.tilt_tolerance).toFixed(1)}°`]);
    rows.push(['on the laser line', ins.on_laser_line ? 'yes: its centre on the visible line' : 'no']);
    rows.push(['hold still', ins.hold_still ? 'yes, until the capture ends' : 'no']);
    if (ins.move.some((v) => v !== 0)) {
      rows.push(['move by', ins.move.map((v, k) => `${'xyz'[k]} ${f1(mm(v))}`).join(', ') + ' mm']);
    }
  }
  rows.push(['sequence', String(ins.sequence)]);
  fillTable($('instr-numbers'), rows);
  fillTable($('calib-counters'), ins.stage ? [
    ['placements kept / planned', `${ins.placements_done} / ${ins.placements_planned}`],
    ['views kept', String(ins.views_captured)],
    ['views rejected', String(ins.views_rejected)],
    ['search views', String(ins.searches)],
  ] : [['no capture running', '']]);
  const reasons = Object.keys(ins.rejected || {});
  fillTable($('rejected-reasons'), reasons.map((r) => [`rejected: ${r}`, String(ins.rejected[r])]));
  $('op-placed').classList.toggle('primary', ins.state === 'place' || ins.state === 'move');
}

function showSigma(p) {
  const body = $('sigma-table').querySelector('tbody');
  if (!p) return;
  body.replaceChildren(...p.parameters.map((q) => {
    const [k, unit] = shownUnit(q.unit, [q.sigma, q.target]);
    const tr = el('tr');
    tr.dataset.name = q.name;
    tr.append(el('td', q.name), el('td', unit),
      el('td', q.sigma === null ? 'not yet' : precise(q.sigma * k), 'num'),
      el('td', precise(q.target === null ? null : q.target * k), 'num'),
      el('td', q.met ? '✓' : '✗', q.met ? 'met' : 'unmet'));
    return tr;
  }));
  const met = $('targets-met');
  met.textContent = p.stage ? (p.targets_met ? `${p.stage}: every target met` : `${p.stage}: not yet`) : 'idle';
  met.className = `badge ${p.targets_met ? 'ok' : 'warn'}`;
  const placements = p.placements_max ? ` (placements ${p.placements_done} of at most ${p.placements_max})` : '';
  $('advice').textContent = (p.advice || '') + placements;
}

// One coverage grid: cells coloured by count (viridis over 1..max), empty cells dark grey.
function drawCoverage(canvas, grid, width, height) {
  if (canvas.width !== width || canvas.height !== height) {
    canvas.width = width;
    canvas.height = height;
  }
  const ctx = canvas.getContext('2d');
  ctx.fillStyle = '#000';
  ctx.fillRect(0, 0, width, height);
  if (!grid || !grid.cols || !grid.rows) return 0;
  const top = Math.max(1, ...grid.cells), rgb = new Float32Array(3);
  const cw = width / grid.cols, ch = height / grid.rows;
  let covered = 0;
  ctx.font = `${Math.max(8, Math.min(12, ch * 0.45))}px sans-serif`;
  ctx.textAlign = 'center';
  ctx.textBaseline = 'middle';
  for (let r = 0; r < grid.rows; r++) {
    for (let c = 0; c < grid.cols; c++) {
      const n = grid.cells[r * grid.cols + c];
      if (n > 0) {
        covered++;
        viridis(top > 1 ? (n - 1) / (top - 1) : 1, rgb, 0);
        ctx.fillStyle = `rgb(${rgb[0] * 255},${rgb[1] * 255},${rgb[2] * 255})`;
      } else {
        ctx.fillStyle = '#2a2f37';
      }
      ctx.fillRect(c * cw + 0.5, r * ch + 0.5, cw - 1, ch - 1);
      if (n > 0 && cw > 16 && ch > 12) {
        ctx.fillStyle = n > 0.6 * top ? '#000' : '#fff';
        ctx.fillText(String(n), (c + 0.5) * cw, (r + 0.5) * ch);
      }
    }
  }
  canvas.dataset.covered = String(covered);
  canvas.dataset.cells = String(grid.cols * grid.rows);
  canvas.dataset.max = String(top);
  return covered;
}

function showCoverage(p, view) {
  if (!p) return;
  const aspect = view && view.width ? view.height / view.width : 0.75;
  const ic = p.image_coverage, vc = p.voltage_coverage;
  const covered = drawCoverage($('coverage-image'), ic, 240, Math.round(240 * aspect));
  $('coverage-image-caption').textContent = ic.cols
    ? `image space: features per cell, ${covered} of ${ic.cols * ic.rows} cells covered` : 'image space: none yet';
  const e = p.voltage_extent, axes = p.voltage_axes.length === 2 ? p.voltage_axes : ['first', 'second'];
  const vcovered = drawCoverage($('coverage-voltage'), vc, 240, 240);
  $('coverage-voltage-caption').textContent = vc.cols
    ? `voltage space: views per cell, ${vcovered} of ${vc.cols * vc.rows} covered; ${axes[0]} ${precise(e[0])}…${precise(e[1])} V (→), ${axes[1]} ${precise(e[2])}…${precise(e[3])} V (↓)`
    : 'voltage space: none yet';
}

function showCalibration(c) {
  showInstruction(c.instruction);
  showSigma(c.progress);
  showCoverage(c.progress, c.view);
}

async function showCalibrationView(meta, payloads) {
  if (meta.stamp === null) return;
  const canvas = $('calib-image');
  const w = meta.width || canvas.width, h = meta.height || canvas.height;
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;
    canvas.height = h;
  }
  const ctx = canvas.getContext('2d');
  if (payloads[1]) {
    const bitmap = await createImageBitmap(new Blob([payloads[1]], { type: 'image/png' }));
    ctx.drawImage(bitmap, 0, 0);
    bitmap.close();
  } else {
    ctx.fillStyle = '#000';
    ctx.fillRect(0, 0, w, h);
  }
  const uv = new Float32Array(payloads[0], 0, 2 * meta.points);
  const colour = meta.accepted ? MARK_KEPT : MARK_REJECTED;
  const r = Math.max(4, w / 120);
  ctx.strokeStyle = colour;
  ctx.fillStyle = colour;
  ctx.lineWidth = Math.max(1.5, w / 480);
  for (let i = 0; i < meta.points; i++) {
    const u = uv[2 * i], v = uv[2 * i + 1];
    ctx.beginPath();
    ctx.arc(u, v, r, 0, 2 * Math.PI);
    ctx.stroke();
    ctx.fillRect(u - 1.5, v - 1.5, 3, 3);   // the centre itself
  }
  if (!meta.accepted) {
    ctx.font = `${Math.round(h / 22)}px sans-serif`;
    ctx.fillStyle = 'rgba(0,0,0,0.6)';
    ctx.fillRect(0, 0, w, h / 14);
    ctx.fillStyle = MARK_REJECTED;
    ctx.textBaseline = 'middle';
    ctx.fillText(`rejected: ${meta.reason || 'no reason given'}`, 8, h / 28);
  }
  canvas.dataset.stamp = String(meta.stamp);
  canvas.dataset.points = String(meta.points);
  canvas.dataset.accepted = String(meta.accepted);
  canvas.dataset.matched = String(meta.matched);
  const verdict = $('view-verdict');
  verdict.textContent = meta.accepted ? 'kept' : `rejected: ${meta.reason || '?'}`;
  verdict.className = `badge ${meta.accepted ? 'ok' : 'error'}`;
  $('view-info').textContent = `${meta.points} points detected, image stamp ${meta.stamp.toFixed(3)} s`;
  const note = $('view-note');
  if (meta.matched) {
    note.textContent = 'Detections drawn on the view\'s own camera frame.';
    note.className = 'dim';
  } else {
    note.textContent = payloads[1]
      ? `The view's own frame was not received: its detections are drawn on the newest frame (stamp ${meta.image_stamp.toFixed(3)} s).`
      : 'No camera image received yet: detections only.';
    note.className = 'warn';
  }
}

async function calibrationViewLoop() {
  if (state.busy.calib) return;
  state.busy.calib = true;
  try {
    while (state.summary.calibration && state.summary.calibration.view
           && state.summary.versions.calibration_view > calib.viewHave) {
      const { meta, payloads } = await fetchFramed('api/calibration/view');
      calib.viewHave = meta.version;
      await showCalibrationView(meta, payloads);
    }
  } catch (err) {
    console.warn('calibration view', err);
  } finally {
    state.busy.calib = false;
  }
}

// A button: the action for the placement of the instruction on screen, through the view's
// server to calibration/operator; the node's answer (or why it was not reached) is shown.
async function sendAction(action) {
  const answer = $('operator-answer');
  const ins = calib.shown;
  if (!ins) {
    answer.textContent = 'No instruction received yet: is a calibration node running?';
    answer.className = 'error';
    return;
  }
  answer.textContent = `${action} (placement ${ins.placement + 1}): sent…`;
  answer.className = 'dim';
  try {
    const response = await fetch(`api/operator?action=${action}&placement=${ins.placement}&sequence=${ins.sequence}`, { method: 'POST' });
    const text = await response.text();
    if (response.ok) {
      const a = JSON.parse(text);
      answer.textContent = `${action} (placement ${ins.placement + 1}): ${a.accepted ? 'accepted' : 'refused'}: ${a.message}`;
      answer.className = a.accepted ? 'ok' : 'error';
      answer.dataset.accepted = String(a.accepted);
    } else {
      answer.textContent = `${action}: not sent (${response.status}): ${text.trim()}`;
      answer.className = 'error';
      answer.dataset.accepted = 'false';
    }
  } catch (err) {
    answer.textContent = `${action}: the view's server did not answer (${err.message})`;
    answer.className = 'error';
  }
  answer.dataset.action = action;
}

function initCalibration() {
  for (const button of document.querySelectorAll('.operator-buttons button')) {
    button.addEventListener('click', () => sendAction(button.dataset.action));
  }
  for (const tab of document.querySelectorAll('#tabs button')) {
    tab.addEventListener('click', () => {
      history.replaceState(null, '', tab.dataset.tab === 'calibration' ? '#calibration' : location.pathname);
      setTab(tab.dataset.tab);
    });
  }
  window.addEventListener('hashchange', () => setTab(location.hash === '#calibration' ? 'calibration' : 'scan'));
  setTab(location.hash === '#calibration' ? 'calibration' : 'scan');
}

initView();
initControls();
initCalibration();
pollLoop();
