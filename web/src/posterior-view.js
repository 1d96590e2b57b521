// The posterior of a job in the scene and the Result panel: the 90 % credible region of the start
// position drawn on the surface under the start area (from the heatmap, the posterior's marginal
// over its cells, or from the posterior samples), the modes with their probability (a click plays
// that past: a simulate job from its start), the per-parameter intervals, the sampler's agreement
// (R-hat) in words, and the physics estimate where it was inferred.
import * as THREE from 'three';

import { credibleCells, gridFromSamples } from './region.js';
import { world } from './stage.js';
import { $, app } from './state.js';

export const LEVEL = 0.9;
const REGION_COLOUR = 0x4fe0ff;

let onPlayMode = () => {};

export function setupPosteriorView({ playMode }) {
  onPlayMode = playMode;
  $('show-region').onchange = () => { if (app.region) app.region.group.visible = $('show-region').checked; };
}

export function clearPosterior() {
  app.region?.group.removeFromParent();
  app.region = null;
  app.modePlaying = null;
  $('posterior-view').innerHTML = '';
}

// The height of the surface under the start area's centre (what the heatmap lies on), else the floor.
function surfaceHeight(grid) {
  const area = app.model.startArea;
  const topZ = area ? Math.max(area.min[2], area.max[2]) : 1;
  const centre = new THREE.Vector3((grid.min[0] + grid.max[0]) / 2, (grid.min[1] + grid.max[1]) / 2, topZ + 0.01);
  world.updateMatrixWorld(true);
  const surfaces = [...app.nodes].filter(([id, node]) => id !== app.model.source && node.visual)
    .map(([, node]) => node.visual);
  const ray = new THREE.Raycaster(world.localToWorld(centre.clone()),
    new THREE.Vector3(0, 0, -1).transformDirection(world.matrixWorld));
  const hit = ray.intersectObjects(surfaces, true).find((h) => h.object.isMesh);
  return hit ? world.worldToLocal(hit.point.clone()).z : 0;
}

// The region of `grid` ({min, max, cells, probability}: heatmap.json's shape) holding LEVEL of its
// mass, as a translucent fill and an outline; `from`: 'heatmap' or 'samples'.
export function showRegion(grid, from) {
  app.region?.group.removeFromParent();
  const { mask, mass, count } = credibleCells(grid.probability, LEVEL);
  const [nx, ny] = grid.cells;
  const dx = (grid.max[0] - grid.min[0]) / nx;
  const dy = (grid.max[1] - grid.min[1]) / ny;
  const z = surfaceHeight(grid) + 0.004;
  const corner = (i, j) => [grid.min[0] + i * dx, grid.min[1] + j * dy, z];
  const fill = [];
  const edges = [];
  const inside = (i, j) => i >= 0 && j >= 0 && i < nx && j < ny && mask[j][i];
  for (let j = 0; j < ny; j += 1) {
    for (let i = 0; i < nx; i += 1) {
      if (!mask[j][i]) continue;
      const [a, b, c, d] = [corner(i, j), corner(i + 1, j), corner(i + 1, j + 1), corner(i, j + 1)];
      fill.push(...a, ...b, ...c, ...a, ...c, ...d);
      if (!inside(i, j - 1)) edges.push(...a, ...b);
      if (!inside(i + 1, j)) edges.push(...b, ...c);
      if (!inside(i, j + 1)) edges.push(...c, ...d);
      if (!inside(i - 1, j)) edges.push(...d, ...a);
    }
  }
  const group = new THREE.Group();
  group.name = 'credible-region';
  const area = new THREE.BufferGeometry();
  area.setAttribute('position', new THREE.Float32BufferAttribute(fill, 3));
  const shade = new THREE.Mesh(area, new THREE.MeshBasicMaterial({
    color: REGION_COLOUR, transparent: true, opacity: 0.3, depthWrite: false, side: THREE.DoubleSide,
  }));
  // the outline as a band a few millimetres wide (a WebGL line is one pixel, lost over a heatmap)
  const band = [];
  const half = Math.max(0.0015, 0.02 * Math.min(dx * nx, dy * ny));
  for (let k = 0; k < edges.length; k += 6) {
    const [ax, ay, , bx, by] = edges.slice(k, k + 6);
    const [ex, ey] = ax === bx ? [half, 0] : [0, half]; // across the edge
    const [sx, sy] = ax === bx ? [0, Math.sign(by - ay) * half] : [Math.sign(bx - ax) * half, 0]; // past its ends
    const p = [[ax - ex - sx, ay - ey - sy], [bx - ex + sx, by - ey + sy], [bx + ex + sx, by + ey + sy],
      [ax + ex - sx, ay + ey - sy]].map(([x, y]) => [x, y, z + 0.001]);
    band.push(...p[0], ...p[1], ...p[2], ...p[0], ...p[2], ...p[3]);
  }
  const outline = new THREE.BufferGeometry();
  outline.setAttribute('position', new THREE.Float32BufferAttribute(band, 3));
  const line = new THREE.Mesh(outline, new THREE.MeshBasicMaterial({
    color: REGION_COLOUR, depthWrite: false, side: THREE.DoubleSide,
  }));
  shade.renderOrder = 4;
  line.renderOrder = 5;
  shade.raycast = () => {};
  line.raycast = () => {};
  group.add(shade, line);
  group.visible = $('show-region').checked;
  world.add(group);
  app.region = { group, from, mass, cells: count, cellCount: nx * ny, area: count * dx * dy, level: LEVEL };
  showRegionLine();
}

// From the posterior samples ([{weight, position}]) over the start area's x-y extent (or theirs).
export function showRegionFromSamples(samples) {
  const grid = gridFromSamples(samples, app.model.startArea);
  if (grid) showRegion(grid, 'samples');
}

// ------------------------------------------------------------------ the Result panel's posterior

const UNITS = { position: 'm', orientation: 'rad', linear_velocity: 'm/s', angular_velocity: 'rad/s', physics: '' };
const NAMES = { position: 'start', orientation: 'turn', linear_velocity: 'velocity', angular_velocity: 'spin',
  physics: '' };

function el(tag, props = {}, ...children) {
  const node = Object.assign(document.createElement(tag), props);
  node.append(...children);
  return node;
}

const num = (x) => {
  const v = Number(x);
  if (!Number.isFinite(v)) return '?';
  const a = Math.abs(v);
  return a !== 0 && (a < 0.001 || a >= 1e5) ? v.toExponential(2) : v.toFixed(a < 1 ? 3 : 2);
};

// The sampler's agreement in words: {kind: 'good' | 'bad' | 'unknown', text}.
export function agreementWords(posterior) {
  const a = posterior?.agreement;
  const runs = posterior?.sampler?.runs;
  if (!a) {
    return { kind: 'unknown', text: `One sampler run${runs === 1 ? ' (too few samples for two)' : ''}: whether `
      + 'the samples found every branch of the posterior is not checked. Draw 20 or more to check.' };
  }
  if (a.runs_agree) {
    return { kind: 'good', text: `The sampler's ${runs ?? 2} independent runs agree (R-hat at most `
      + `${Number(a.max_rhat).toFixed(2)}, ≤ ${a.limit}): the samples, intervals and region can be trusted.` };
  }
  return { kind: 'bad', text: `The sampler's independent runs disagree (R-hat up to ${Number(a.max_rhat).toFixed(2)} `
    + `> ${a.limit}): they found different parts of the posterior. Do not trust these samples, intervals or `
    + 'region; draw more samples or narrow the prior.' };
}

function modeText(mode, k) {
  const s = mode.initial_state;
  const p = s.position.map((v) => v.toFixed(2)).join(', ');
  const speed = Math.hypot(...s.linear_velocity);
  const spin = Math.hypot(...s.angular_velocity);
  const share = mode.probability == null ? '' : `${Math.round(100 * mode.probability)} %: `;
  return `${k + 1}. ${share}from (${p}) at ${speed.toFixed(2)} m/s${spin > 0.05 ? `, ${spin.toFixed(1)} rad/s` : ''}`;
}

// result.json's posterior (and physics) in the panel.
export function showPosteriorSummary(result) {
  const view = $('posterior-view');
  view.innerHTML = '';
  if (!result) return;
  const post = result.posterior;
  if (post) {
    const words = agreementWords(post);
    view.append(el('h3', { textContent: `Posterior: ${post.samples} samples` }),
      el('div', { className: `agreement ${words.kind}`, textContent: words.text }));
  }
  const modes = post?.modes?.length ? post.modes : (result.search?.modes ?? []);
  if (modes.length) {
    const title = post?.modes?.length ? 'Pasts that explain it (click: play)'
      : 'Pasts the search found (click: play; samples give their probability)';
    const list = el('ol', { id: 'modes' });
    modes.forEach((mode, k) => {
      const button = el('button', { textContent: modeText(mode, k), title: 'play this past (a simulate job from its start)' });
      button.dataset.mode = String(k);
      button.classList.toggle('on', app.modePlaying === k);
      button.onclick = () => onPlayMode(mode, k);
      list.append(el('li', {}, button));
    });
    view.append(el('h3', { textContent: title }), list);
  }
  if (post?.intervals && Object.keys(post.intervals).length) view.append(...intervalTable(post.intervals));
  if (result.physics) view.append(...physicsLines(result.physics));
  showRegionLine();
}

function intervalTable(intervals) {
  const table = el('table', { id: 'intervals' });
  table.append(el('tr', {}, el('th', { textContent: 'parameter' }), el('th', { textContent: 'median' }),
    el('th', { textContent: '90 % interval' }), el('th', { textContent: '' })));
  for (const [name, iv] of Object.entries(intervals)) {
    const [block, axis] = name.split('.');
    const unit = UNITS[block] ?? '';
    const label = block === 'physics' ? axis : `${NAMES[block] ?? block} ${axis}`;
    const [lo, hi] = iv['90%'];
    const [lo50, hi50] = iv['50%'];
    const span = hi - lo || 1;
    const bar = el('div', { className: 'bar' },
      Object.assign(el('span'), { style: `left:${(100 * (lo50 - lo)) / span}%;width:${(100 * (hi50 - lo50)) / span}%` }),
      Object.assign(el('i'), { style: `left:calc(${(100 * (iv.median - lo)) / span}% - 1px)` }));
    const row = el('tr', { title: `${name}: 50 % [${num(lo50)}, ${num(hi50)}]${iv.rhat ? `, R-hat ${iv.rhat.toFixed(2)}` : ''}`
      + `${iv.ess ? `, ESS ${Math.round(iv.ess)}` : ''}` },
    el('td', { textContent: `${label}${unit ? ` (${unit})` : ''}` }), el('td', { className: 'num', textContent: num(iv.median) }),
    el('td', { className: 'num', textContent: `${num(lo)} … ${num(hi)}` }), el('td', {}, bar));
    row.dataset.parameter = name;
    table.append(row);
  }
  return [el('h3', { textContent: 'Intervals (median, 90 %; bar: 50 %)' }), table];
}

function physicsLines(physics) {
  const lines = [el('h3', { textContent: 'Physics, inferred' })];
  const list = el('ul', { id: 'physics' });
  for (const name of physics.inferred ?? []) {
    const iv = physics.intervals?.[name];
    const best = physics.most_probable?.[name];
    const text = `${name}: ${num(best)}${iv ? ` (90 %: ${num(iv['90%'][0])} … ${num(iv['90%'][1])})` : ' (draw samples for an interval)'}`;
    list.append(el('li', { textContent: text }));
  }
  lines.push(list);
  return lines;
}

function showRegionLine() {
  const view = $('posterior-view');
  view.querySelector('.region')?.remove();
  if (!app.region) return;
  const cm2 = app.region.area * 1e4;
  const from = app.region.from === 'heatmap' ? 'the heatmap' : 'the samples';
  view.prepend(el('div', { className: 'region muted',
    textContent: `90 % region (cyan, on the surface under the start area): ${cm2 < 100 ? cm2.toFixed(1) : Math.round(cm2)} cm² of the start `
      + `area, ${app.region.cells} of ${app.region.cellCount} cells, from ${from}` }));
}
