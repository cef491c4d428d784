"""The explorer page's HTML, style and script (no network, no libraries).

`explore.write_page` replaces __TITLE__ and __DATA__ (the page's JSON, see
`explore.page_data`). The script draws frame t of every tile from its strip
(all frames side by side, one PNG), so every tile plays in sync; state for
tests: `document.body.dataset.frame`, and the counterfactual panel's
`data-slot` / `data-kind` / `data-source`.
"""

TEMPLATE = r"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<link rel="icon" href="data:,">
<title>__TITLE__</title>
<style>
body { font: 13px/1.35 system-ui, sans-serif; margin: 12px 16px; color: #222; background: #fafafa; }
h1 { font-size: 17px; margin: 0 0 6px; }
h2 { font-size: 14px; margin: 14px 0 4px; }
.bar { display: flex; flex-wrap: wrap; gap: 6px; align-items: center; margin: 4px 0; }
button { font: inherit; padding: 2px 8px; border: 1px solid #999; background: #fff; border-radius: 3px; cursor: pointer; }
button.on { background: #234; color: #fff; border-color: #234; }
#frame-label { font-variant-numeric: tabular-nums; min-width: 16em; font-weight: 600; }
.observed #frame-label { color: #3c9a3c; } .predicted #frame-label { color: #d22; }
#slider { width: 320px; }
.row { display: flex; flex-wrap: wrap; gap: 8px; align-items: flex-start; }
figure.tile { margin: 0; text-align: center; }
figure.tile figcaption { font-size: 12px; white-space: nowrap; }
canvas { display: block; image-rendering: pixelated; border: 3px solid #3c9a3c; background: #fff; }
.predicted canvas { border-color: #d22; }
.slot { border: 2px solid transparent; padding: 3px; border-radius: 4px; cursor: pointer; background: #fff; }
.slot.selected { border-color: #234; box-shadow: 0 0 0 2px #234; }
.slot .name { font-weight: 600; }
.swatch { display: inline-block; width: 10px; height: 10px; border-radius: 2px; margin-right: 3px; vertical-align: -1px; }
.slot .pair { display: flex; gap: 3px; }
#counterfactual { background: #fff; border: 1px solid #ccc; padding: 6px; border-radius: 4px; display: inline-block; }
.note { color: #666; font-size: 12px; }
.charts { display: flex; flex-wrap: wrap; gap: 10px; }
.legend { flex-basis: 100%; font-weight: 600; }
svg.chart { background: #fff; border: 1px solid #ddd; }
svg.chart text { font-size: 10px; fill: #333; }
footer { margin-top: 16px; border-top: 1px solid #ccc; padding-top: 6px; }
footer pre { font-size: 11px; white-space: pre-wrap; margin: 4px 0; }
</style>
</head>
<body>
<script id="explorer-data" type="application/json">__DATA__</script>
<h1 id="title"></h1>
<div class="note" id="subtitle"></div>
<div class="bar" id="videos"></div>
<div class="bar">
  <button id="play">pause</button>
  <input id="slider" type="range" min="0" value="0">
  <span id="frame-label"></span>
</div>
<h2>Rollouts</h2>
<div class="row" id="rollouts"></div>
<h2><span id="primary-slots"></span> <span class="note">(click a slot for its counterfactual rollouts)</span></h2>
<div class="row" id="slots"></div>
<h2>Counterfactual</h2>
<div class="bar" id="kinds"></div>
<div id="counterfactual"><div class="row" id="cf-tiles"></div><div class="note" id="cf-note"></div></div>
<h2>Per-step metrics</h2>
<div class="note" id="run-note"></div>
<div class="charts" id="run-charts"></div>
<div class="note" id="video-note">this video</div>
<div class="charts" id="video-charts"></div>
<footer><div class="note" id="footer-note"></div><pre id="identity"></pre></footer>
<script>
"use strict";
const D = JSON.parse(document.getElementById('explorer-data').textContent);
const T = D.burn_in + D.rollout;
const W = D.width, H = D.height, S = D.scale;
const SLOT_SCALE = Math.max(1, S - 1);  // the slots' tiles a little smaller: all N in a row
const state = {video: 0, frame: 0, playing: true, slot: 0, kind: 'remove'};
let tiles = [];  // [canvas, image]
const images = new Map();
// One colour per method in every chart (dashed: the slot model's own reconstruction).
const METHOD_COLOURS = {...D.method_colours, [D.reference.label]: D.reference.colour};
const SPARE_COLOURS = ['#9467bd', '#8c564b', '#e377c2', '#17becf'];
// Names come from eval/metrics.json (a run folder someone shares): looked
// up as own keys only ('constructor' is no colour), shown as text only.
function lookup(table, key) { return Object.prototype.hasOwnProperty.call(table, key) ? table[key] : undefined; }
function colour(name, j) { return lookup(METHOD_COLOURS, name) || SPARE_COLOURS[j % SPARE_COLOURS.length]; }
const KIND_TEXT = {remove: 'removed', freeze: 'frozen'};
const METRIC_NAMES = D.metric_labels;

function el(tag, attrs, children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === 'text') node.textContent = v; else node.setAttribute(k, v);
  }
  for (const child of children || []) node.appendChild(child);
  return node;
}

function image(uri) {
  if (!images.has(uri)) {
    const img = new Image();
    img.onload = () => drawAll();
    img.src = uri;
    images.set(uri, img);
  }
  return images.get(uri);
}

function tile(label, uri, key, scale) {
  const canvas = el('canvas', {width: W * (scale || S), height: H * (scale || S)});
  if (key) canvas.dataset.source = key;
  tiles.push([canvas, image(uri)]);
  return el('figure', {class: 'tile'}, [el('figcaption', {text: label}), canvas]);
}

function draw(canvas, img) {
  const ctx = canvas.getContext('2d');
  ctx.imageSmoothingEnabled = false;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (img.complete && img.naturalWidth) {
    ctx.drawImage(img, state.frame * W, 0, W, H, 0, 0, canvas.width, canvas.height);
  }
}

function drawAll() {
  tiles = tiles.filter(([canvas]) => canvas.isConnected);
  for (const [canvas, img] of tiles) draw(canvas, img);
  const t = state.frame, observed = t < D.burn_in;
  document.body.classList.toggle('observed', observed);
  document.body.classList.toggle('predicted', !observed);
  document.body.dataset.frame = String(t);
  document.getElementById('slider').value = String(t);
  document.getElementById('frame-label').textContent = observed
      ? `burn-in frame ${t + 1}/${D.burn_in} (observed)`
      : `rollout step ${t - D.burn_in + 1}/${D.rollout} (predicted)`;
  for (const line of document.querySelectorAll('line.marker')) {
    const x = line.dataset['x' + (t - D.burn_in + 1)];
    line.setAttribute('visibility', x === undefined ? 'hidden' : 'visible');
    if (x !== undefined) { line.setAttribute('x1', x); line.setAttribute('x2', x); }
  }
}

function video() { return D.videos[state.video]; }

function buildRollouts() {
  const row = document.getElementById('rollouts');
  row.replaceChildren(...video().rows.map(r => tile(r.label, r.strip, r.key)));
}

function buildSlots() {
  const row = document.getElementById('slots');
  row.replaceChildren(...video().slots.map((slot, k) => {
    const name = el('div', {class: 'name'}, [
        el('span', {class: 'swatch', style: `background:${D.palette[k % D.palette.length]}`}),
        document.createTextNode(`slot ${k}`)]);
    const card = el('div', {class: 'slot' + (k === state.slot ? ' selected' : ''),
                            'data-slot': String(k), id: `slot-${k}`}, [
        name, el('div', {class: 'pair'}, [tile('view', slot.view, null, SLOT_SCALE),
                                          tile('alpha', slot.alpha, null, SLOT_SCALE)])]);
    card.addEventListener('click', () => selectSlot(k));
    return card;
  }));
}

function buildCounterfactual() {
  const v = video(), k = state.slot, kind = state.kind;
  const cf = v.counterfactual[kind][k];
  const factual = v.rows.find(r => r.key === D.primary.key);
  const panel = document.getElementById('counterfactual');
  panel.dataset.slot = String(k);
  panel.dataset.kind = kind;
  const what = `slot ${k} ${KIND_TEXT[kind]}`;
  document.getElementById('cf-tiles').replaceChildren(
      tile(`${D.primary.label} (factual)`, factual.strip, 'factual'),
      tile('factual masks', v.factual_masks, 'factual_masks'),
      tile(what, cf.frames, `${kind}/${k}`),
      tile(`${what}: masks`, cf.masks, `${kind}/${k}/masks`),
      tile(`|difference| x${D.diff_gain}`, cf.diff, `${kind}/${k}/diff`));
  const how = kind === 'remove'
      ? `slot ${k} deleted from every burn-in frame: masked out of ${D.primary.label}'s attention and dropped from the decoder's softmax over slots`
      : `slot ${k} held at its last observed value while the others are predicted`;
  document.getElementById('cf-note').textContent =
      `${how}. Largest per-pixel difference from the factual rollout: ${cf.max_diff}.`;
  for (const b of document.querySelectorAll('#kinds button')) b.classList.toggle('on', b.dataset.kind === kind);
}

function selectSlot(k) {
  state.slot = k;
  for (const card of document.querySelectorAll('.slot')) card.classList.toggle('selected', card.dataset.slot === String(k));
  buildCounterfactual();
  drawAll();
}

function selectKind(kind) { state.kind = kind; buildCounterfactual(); drawAll(); }

const SVG = 'http://www.w3.org/2000/svg';

// An SVG element; `text` becomes a text node (never markup).
function svg(tag, attrs, text) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, String(v));
  if (text !== undefined) node.textContent = String(text);
  return node;
}

function chart(title, series) {
  const width = 250, height = 150, left = 38, right = 8, top = 16, bottom = 26;
  const names = Object.keys(series);
  const values = names.flatMap(n => series[n]).filter(v => typeof v === 'number' && isFinite(v));
  const root = svg('svg', {class: 'chart', width, height});
  root.appendChild(svg('text', {x: width / 2, y: 11, 'text-anchor': 'middle', 'font-weight': '600'}, title));
  if (!values.length) { root.appendChild(svg('text', {x: 40, y: 70}, 'no values')); return root; }
  let lo = Math.min(...values), hi = Math.max(...values);
  if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
  const steps = Math.max(...names.map(n => series[n].length));
  const x = i => left + (steps > 1 ? i / (steps - 1) : 0.5) * (width - left - right);
  const y = v => top + (1 - (v - lo) / (hi - lo)) * (height - top - bottom);
  root.append(
      svg('line', {x1: left, y1: height - bottom, x2: width - right, y2: height - bottom, stroke: '#999'}),
      svg('line', {x1: left, y1: top, x2: left, y2: height - bottom, stroke: '#999'}),
      svg('text', {x: left - 3, y: top + 4, 'text-anchor': 'end'}, hi.toFixed(2)),
      svg('text', {x: left - 3, y: height - bottom, 'text-anchor': 'end'}, lo.toFixed(2)),
      svg('text', {x: left, y: height - bottom + 11}, '1'),
      svg('text', {x: width - right, y: height - bottom + 11, 'text-anchor': 'end'}, String(steps)),
      svg('text', {x: (left + width) / 2, y: height - 3, 'text-anchor': 'middle'}, 'rollout step'));
  const marker = svg('line', {class: 'marker', y1: top, y2: height - bottom, stroke: '#d22',
                              'stroke-dasharray': '3,2', visibility: 'hidden'});
  for (let i = 0; i < steps; i++) marker.setAttribute(`data-x${i + 1}`, x(i).toFixed(1));
  root.appendChild(marker);
  names.forEach((name, j) => {
    let path = '', pen = false;
    series[name].forEach((v, i) => {
      if (typeof v !== 'number' || !isFinite(v)) { pen = false; return; }
      path += `${pen ? 'L' : 'M'}${x(i).toFixed(1)},${y(v).toFixed(1)}`; pen = true;
    });
    const line = svg('path', {d: path, fill: 'none', stroke: colour(name, j), 'stroke-width': 1.5});
    if (name.includes('recon')) line.setAttribute('stroke-dasharray', '4,2');
    root.appendChild(line);
  });
  return root;
}

function charts(target, curves) {
  const entries = Object.entries(curves || {});
  const names = [...new Set(entries.flatMap(([, series]) => Object.keys(series)))];
  const children = [];
  if (names.length) {
    const legend = el('div', {class: 'legend'});
    names.forEach((name, j) => {
      legend.append(el('span', {style: `color:${colour(name, j)}`, text: `\u2501\u2501 ${name}`}),
                    document.createTextNode('\u00a0 '));
    });
    children.push(legend);
  }
  for (const [metric, series] of entries) children.push(chart(lookup(METRIC_NAMES, metric) || metric, series));
  document.getElementById(target).replaceChildren(...children);
}

function selectVideo(i) {
  state.video = i;
  for (const b of document.querySelectorAll('#videos button')) b.classList.toggle('on', b.dataset.video === String(i));
  buildRollouts(); buildSlots(); buildCounterfactual();
  charts('video-charts', video().curves);
  document.getElementById('video-note').textContent = `this video (#${video().index}), per rollout step`;
  drawAll();
}

function setup() {
  document.title = D.title;
  document.getElementById('primary-slots').textContent = `${D.primary.label}'s slots`;
  document.getElementById('title').textContent = D.title;
  document.getElementById('subtitle').textContent =
      `${D.videos.length} ${D.split} videos, ${D.burn_in} observed frames (green) then ${D.rollout} predicted (red); ` +
      `${D.num_slots} slots, slot views: ${D.slot_views}.`;
  const videos = document.getElementById('videos');
  videos.appendChild(el('span', {text: 'video:'}));
  D.videos.forEach((v, i) => {
    const b = el('button', {'data-video': String(i), id: `video-${i}`, text: `#${v.index}`});
    b.addEventListener('click', () => selectVideo(i));
    videos.appendChild(b);
  });
  const kinds = document.getElementById('kinds');
  kinds.appendChild(el('span', {text: 'intervention:'}));
  for (const kind of ['remove', 'freeze']) {
    const b = el('button', {'data-kind': kind, id: `kind-${kind}`, text: kind});
    b.addEventListener('click', () => selectKind(kind));
    kinds.appendChild(b);
  }
  const slider = document.getElementById('slider');
  slider.max = String(T - 1);
  slider.addEventListener('input', () => { state.frame = Number(slider.value); state.playing = false; updatePlay(); drawAll(); });
  document.getElementById('play').addEventListener('click', () => { state.playing = !state.playing; updatePlay(); });
  document.getElementById('run-note').textContent = D.run_curves_note;
  charts('run-charts', D.run_curves);
  document.getElementById('footer-note').textContent =
      `Made from (run ids and steps; as render/identity.json), computed in ${D.seconds} s:`;
  document.getElementById('identity').textContent = Object.entries(D.identity).map(
      ([key, value]) => `${key}: ${JSON.stringify(value)}`).join('\n');
  selectVideo(0);
  setInterval(() => { if (state.playing) { state.frame = (state.frame + 1) % T; drawAll(); } }, 1000 / D.fps);
}

function updatePlay() { document.getElementById('play').textContent = state.playing ? 'pause' : 'play'; }

window.explorer = {state, selectSlot, selectKind, selectVideo};
setup();
</script>
</body>
</html>
"""
