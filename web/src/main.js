// The DejaView web viewer: load a scene, set up the problem, run jobs on the service, watch results.
// Test hooks: window.dejaview (state(), loadScenePath(), setPose(), run(), ...).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { TransformControls } from 'three/addons/controls/TransformControls.js';

import { LossChart } from './chart.js';
import { Connection, serverFetch, socketUrl } from './connection.js';
import { loadMesh, parseSpheres, primitiveGeometry, spheresMesh } from './geometry.js';
import {
  buildObservation, highlightObservation, observationLine, updateObservationLine,
} from './observations.js';
import {
  applyPose, heatmapDecal, observationTimes, parsePosterior, parsePosteriorPaths, parseTrajectory, sampleCloud,
  samplePaths, summarizeResult, trajectorySpline,
} from './results.js';
import { SceneModel } from './scene-xml.js';
import { setupVR } from './vr.js';

const $ = (id) => document.getElementById(id);
const TARGET = '#target'; // selection id of the target ghost (the last observation)
const OBSERVATION = '#target:'; // selection ids of the other observations: '#target:<index>'
// playback lights an observation up from a little before its time until a little after (at most
// halfway to the next observation's time)
const HIGHLIGHT_BEFORE_S = 0.03;
const HIGHLIGHT_AFTER_S = 0.25;
const PALETTE = [0x5b8fd9, 0x2ca02c, 0x9467bd, 0x17becf, 0xbcbd22, 0xe377c2, 0x8c564b];
const SOURCE_COLOUR = 0xff7f0e;
const FIXED_COLOUR = 0x8a8f98;

// ------------------------------------------------------------------ three.js set-up
const viewport = $('viewport');
const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(Math.min(2, window.devicePixelRatio));
viewport.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1b1f27);
const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 200);
camera.position.set(1.8, 1.4, 2.2);
const orbit = new OrbitControls(camera, renderer.domElement);
orbit.target.set(0, 0.4, 0);
orbit.update();

scene.add(new THREE.HemisphereLight(0xddeeff, 0x202020, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(3, 6, 2);
scene.add(sun);
const grid = new THREE.GridHelper(10, 40, 0x556070, 0x343b48);
grid.position.y = 0.001;
scene.add(grid);

// The scene's frame is z-up; three's (and WebXR's) is y-up: everything of the scene lives in `world`.
const world = new THREE.Group();
world.rotation.x = -Math.PI / 2;
scene.add(world);

const gizmo = new TransformControls(camera, renderer.domElement);
gizmo.setSize(0.8);
scene.add(gizmo.getHelper());
gizmo.addEventListener('dragging-changed', (e) => { orbit.enabled = !e.value; });
gizmo.addEventListener('objectChange', () => poseEdited(gizmo.object));

function resize() {
  const w = viewport.clientWidth || 1;
  const h = viewport.clientHeight || 1;
  renderer.setSize(w, h);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();

// ------------------------------------------------------------------ application state
const app = {
  model: null,
  nodes: new Map(), // id -> {group, visual, packing}
  files: null, // uploaded files by name, or null: meshes come from the server's scene root
  ghost: null, // the target: a translucent copy of the source at the last observed pose
  observations: [], // every <target>: {index, id, group, label, ...} (observations.js)
  observationLine: null, // dashed line through them in time order
  selected: null,
  trajectory: null,
  path: null,
  heatmap: null,
  heatmapGrid: null,
  samples: null, // the posterior samples' start points (THREE.Points)
  samplePaths: null, // a few posterior samples' trajectories (THREE.Group of faint lines)
  time: 0,
  playing: false,
  jobs: new Map(), // job_id -> {kind, state, requestId}
  requests: new Map(), // request_id -> kind
  current: null, // the job the chart follows
  result: null,
  notifications: [],
  loading: null,
  startArea: null,
};
const chart = new LossChart($('loss'));
chart.draw();

function notify(text, kind = 'info') {
  app.notifications.push({ kind, text, at: Date.now() });
  const li = document.createElement('li');
  li.className = kind;
  li.textContent = text;
  $('notifications').prepend(li);
  while ($('notifications').children.length > 8) $('notifications').lastChild.remove();
  setTimeout(() => li.remove(), kind === 'error' ? 20000 : 8000);
}

// ------------------------------------------------------------------ poses between model and three
const toQuat = ([w, x, y, z]) => new THREE.Quaternion(x, y, z, w).normalize();
const fromQuat = (q) => [q.w, q.x, q.y, q.z];

function placeFromModel(id) {
  const node = app.nodes.get(id);
  const obj = app.model.object(id);
  node.group.position.set(...obj.position);
  node.group.quaternion.copy(toQuat(obj.orientation));
}

// Every observation at its observed pose (a position-only one unturned).
function placeObservations() {
  if (!app.model) return;
  const targets = app.model.targets;
  for (const obs of app.observations) {
    const target = targets[obs.index];
    if (!target || obs.group.parent !== world) continue; // not while held in VR
    obs.group.position.set(...target.position);
    obs.group.quaternion.copy(toQuat(target.orientation ?? [1, 0, 0, 0]));
  }
  if (app.observationLine) updateObservationLine(app.observationLine, app.observations);
}

// The selection id of an observation: the last one is the target, TARGET.
const observationId = (target) => (target.last ? TARGET : `${OBSERVATION}${target.index}`);
const isObservation = (id) => typeof id === 'string' && (id === TARGET || id.startsWith(OBSERVATION));

function observationOf(id) {
  if (id === TARGET) return app.observations.find((o) => o.last) || null;
  if (isObservation(id)) return app.observations.find((o) => o.index === Number(id.slice(OBSERVATION.length))) || null;
  return null;
}

// The group a selection id moves: an object's, or an observation's.
function groupOf(id) {
  return isObservation(id) ? observationOf(id)?.group ?? null : app.nodes.get(id)?.group ?? null;
}

// A gizmo or a VR controller moved `group`: write its pose into the scene.
function poseEdited(group) {
  if (!group || !app.model) return;
  const pos = group.position.toArray();
  const quat = fromQuat(group.quaternion);
  if (group.userData.observation !== undefined) {
    app.model.setTarget(pos, quat, group.userData.observation);
    if (app.observationLine) updateObservationLine(app.observationLine, app.observations);
  } else {
    app.model.setPose(group.userData.objectId, pos, quat);
  }
  updateSelectionText();
}

// ------------------------------------------------------------------ loading a scene
function fileUrl(name) {
  if (app.files) {
    const file = app.files.get(name) || app.files.get(name.split('/').pop());
    if (!file) throw new Error(`${name}: not among the uploaded files`);
    return URL.createObjectURL(file);
  }
  return `files/${app.model.rootPath(name).split('/').map(encodeURIComponent).join('/')}`;
}

function material(id) {
  const colour = colourOf(id);
  return new THREE.MeshStandardMaterial({ color: colour, roughness: 0.7, metalness: 0.05,
    side: app.model.object(id).shape === 'plane' ? THREE.DoubleSide : THREE.FrontSide,
    transparent: app.model.object(id).shape === 'plane', opacity: 0.6 });
}

function colourOf(id) {
  if (id === app.model.source) return SOURCE_COLOUR;
  if (app.model.isFixed(id)) return FIXED_COLOUR;
  const movable = app.model.objects.filter((o) => !app.model.isFixed(o.id) && o.id !== app.model.source);
  return PALETTE[Math.max(0, movable.findIndex((o) => o.id === id)) % PALETTE.length];
}

function recolour() {
  for (const [id, node] of app.nodes) {
    node.visual?.traverse((m) => { if (m.isMesh) m.material.color.setHex(colourOf(id)); });
  }
}

async function buildObject(obj) {
  const group = new THREE.Group();
  group.userData.objectId = obj.id;
  world.add(group);
  const node = { group, visual: null, packing: null };
  app.nodes.set(obj.id, node);
  placeFromModel(obj.id);
  const mat = material(obj.id);
  if (obj.mesh) {
    node.visual = await loadMesh(fileUrl(obj.mesh), obj.mesh, mat);
  } else if (obj.robot) {
    node.visual = await loadRobot(obj, mat);
  } else {
    node.visual = new THREE.Mesh(primitiveGeometry(obj), mat);
  }
  node.visual.traverse((m) => { m.userData.objectId = obj.id; });
  group.add(node.visual);
  if (obj.spheres) {
    try {
      const response = await serverFetch(fileUrl(obj.spheres));
      if (!response.ok) throw new Error(`HTTP ${response.status}`);
      node.packing = spheresMesh(parseSpheres(await response.text()), colourOf(obj.id));
      node.packing.visible = $('show-spheres').checked;
      node.visual.visible = !$('show-spheres').checked;
      group.add(node.packing);
    } catch (err) {
      notify(`${obj.id}: sphere packing ${obj.spheres}: ${err.message}`, 'error');
    }
  }
}

// A robot (urdf= or mjcf=): the server poses its links by forward kinematics (GET robot-links/SCENE),
// in the robot's frame, so the object's group (its <pose>) carries them all.
async function loadRobot(obj, mat) {
  const group = new THREE.Group();
  group.userData.robotLinks = [];
  if (app.files || !app.model.origin) {
    throw new Error('robots are drawn from scenes in the server\'s scene root (the server poses the links)');
  }
  const path = app.model.origin.split('/').map(encodeURIComponent).join('/');
  const response = await serverFetch(`robot-links/${path}?object=${encodeURIComponent(obj.id)}`);
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    throw new Error(`robot links: ${body.message || body.error?.message || `HTTP ${response.status}`}`);
  }
  for (const link of (await response.json()).links) {
    const part = link.shape === 'mesh'
      ? await loadMesh(`files/${link.mesh.split('/').map(encodeURIComponent).join('/')}`, link.mesh, mat)
      : new THREE.Mesh(primitiveGeometry({ id: link.name, ...link }), mat);
    if (link.shape === 'mesh') part.scale.setScalar(link.scale);
    part.position.set(...link.position);
    part.quaternion.copy(toQuat(link.orientation));
    part.name = link.name;
    group.add(part);
    group.userData.robotLinks.push(link.name);
  }
  return group;
}

// The start area (a box that bounds the initial position) as a wire box; a flat area as a square.
function buildStartArea() {
  if (app.startArea) app.startArea.removeFromParent();
  app.startArea = null;
  const area = app.model.startArea;
  if (!area) return;
  const size = area.max.map((v, i) => Math.max(0.002, v - area.min[i]));
  const box = new THREE.LineSegments(new THREE.EdgesGeometry(new THREE.BoxGeometry(...size)),
    new THREE.LineBasicMaterial({ color: 0x2ca02c }));
  box.position.set(...area.min.map((v, i) => (v + area.max[i]) / 2));
  box.name = 'start-area';
  world.add(box);
  app.startArea = box;
}

// Every observation of the source: a translucent copy at each observed pose, a marker where only
// the position was seen, each labelled with its time; the last one (the "Target") in the source's
// colour as before, app.ghost. Rebuilt when the source or the observations change.
function buildObservations() {
  removeObservations();
  const source = app.model.source && app.nodes.get(app.model.source);
  if (!source?.visual) return;
  const box = new THREE.Box3().setFromObject(source.visual, true);
  const radius = box.isEmpty() ? 0.05 : box.getSize(new THREE.Vector3()).length() / 2;
  const targets = app.model.targets;
  app.observations = targets.map((target) => {
    const obs = buildObservation(target, source.visual, radius, observationId(target));
    world.add(obs.group, obs.label);
    return obs;
  });
  app.ghost = app.observations.find((o) => o.last)?.group ?? null;
  placeObservations();
  if (app.observations.length > 1) {
    app.observationLine = observationLine(app.observations, targets);
    world.add(app.observationLine);
  }
  placeLabels();
}

function removeObservations() {
  for (const obs of app.observations) {
    obs.group.removeFromParent();
    obs.label.removeFromParent();
  }
  app.observationLine?.removeFromParent();
  app.observations = [];
  app.observationLine = null;
  app.ghost = null;
}

// Each label above its observation (in the scene's z), wherever the observation is now; labels
// that would cover one another on the screen are stacked upwards (nearest the floor first).
const labelAt = new THREE.Vector3();
function placeLabels() {
  const height = renderer.domElement.clientHeight || 1;
  const width = renderer.domElement.clientWidth || 1;
  const boxes = [];
  for (const obs of app.observations) {
    world.worldToLocal(obs.group.getWorldPosition(labelAt));
    obs.label.position.set(labelAt.x, labelAt.y, labelAt.z + obs.labelLift);
    obs.label.visible = obs.group.visible;
    obs.label.center.y = 0;
    if (!obs.label.visible) continue;
    // the label's box on the screen (pixels, y down): sizeAttenuation off, so its height in NDC is
    // scale.y times the projection's y scale
    const p = obs.label.getWorldPosition(labelAt).project(camera);
    if (p.z > 1) continue;
    const h = ((obs.label.scale.y * camera.projectionMatrix.elements[5]) / 2) * height;
    const w = (h * obs.label.scale.x) / obs.label.scale.y;
    boxes.push({ obs, x: ((p.x + 1) / 2) * width, bottom: ((1 - p.y) / 2) * height, w, h });
  }
  boxes.sort((a, b) => b.bottom - a.bottom);
  const placed = [];
  for (const box of boxes) {
    let bottom = box.bottom;
    for (let moved = true; moved;) {
      moved = false;
      for (const other of placed) {
        const apartX = Math.abs(box.x - other.x) >= (box.w + other.w) / 2 + 2;
        const apartY = bottom <= other.bottom - other.h - 2 || bottom - box.h >= other.bottom + 2;
        if (!apartX && !apartY) {
          bottom = other.bottom - other.h - 2;
          moved = true;
        }
      }
    }
    box.obs.label.center.y = -(box.bottom - bottom) / box.h;
    placed.push({ ...box, bottom });
  }
}

// Light up the observations whose time the playback is passing (t: seconds; null: none).
function highlightObservations(t) {
  const times = t == null ? [] : observationTimes(app.model?.targets ?? [], app.result, app.trajectory?.duration);
  const sorted = times.filter((x) => x != null).sort((a, b) => a - b);
  for (const obs of app.observations) {
    const at = times[obs.index];
    const next = sorted.find((x) => x > at);
    const after = next === undefined ? HIGHLIGHT_AFTER_S : Math.min(HIGHLIGHT_AFTER_S, (next - at) / 2);
    highlightObservation(obs, at != null && t >= at - HIGHLIGHT_BEFORE_S && t <= at + after);
  }
}

function clearScene() {
  gizmo.detach();
  clearResults();
  app.startArea?.removeFromParent();
  for (const node of app.nodes.values()) world.remove(node.group);
  removeObservations();
  app.nodes.clear();
  app.selected = null;
}

function clearResults() {
  for (const key of ['path', 'heatmap', 'samples', 'samplePaths']) {
    if (app[key]) app[key].removeFromParent();
    app[key] = null;
  }
  app.trajectory = null;
  app.heatmapGrid = null;
  app.result = null;
  app.playing = false;
  app.time = 0;
  showResultSummary(null);
  highlightObservations(null);
  updatePlayback();
}

async function loadScene(text, origin = '', files = null) {
  const model = new SceneModel(text, origin);
  clearScene();
  app.model = model;
  app.files = files;
  const loading = Promise.all(model.objects.map((obj) => buildObject(obj).catch((err) => {
    notify(`${obj.id}: ${err.message}`, 'error');
  })));
  app.loading = loading;
  await loading;
  buildObservations();
  buildStartArea();
  recolour();
  fitCamera();
  fillPanel();
  $('scene-name').textContent = `${model.name}${origin ? ` (${origin})` : ''}: ${model.objects.length} objects`;
  notify(`loaded ${model.name}`);
  return model.objects.map((o) => o.id);
}

async function loadScenePath(path) {
  const response = await serverFetch(`files/${path.split('/').map(encodeURIComponent).join('/')}`);
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status}`);
  return loadScene(await response.text(), path);
}

function fitCamera() {
  const box = new THREE.Box3();
  for (const [id, node] of app.nodes) {
    if (app.model.object(id).shape !== 'plane') box.expandByObject(node.group);
  }
  for (const obs of app.observations) box.expandByObject(obs.group);
  if (box.isEmpty()) return;
  const centre = box.getCenter(new THREE.Vector3());
  const size = Math.max(0.5, box.getSize(new THREE.Vector3()).length());
  orbit.target.copy(centre);
  camera.position.copy(centre).add(new THREE.Vector3(0.75, 0.55, 0.9).multiplyScalar(size * 1.1));
  camera.near = size / 200;
  camera.far = size * 100;
  camera.updateProjectionMatrix();
  orbit.update();
}

// ------------------------------------------------------------------ panel
function fillPanel() {
  const body = $('objects').querySelector('tbody');
  body.innerHTML = '';
  for (const obj of app.model.objects) {
    const tr = document.createElement('tr');
    tr.dataset.id = obj.id;
    const id = document.createElement('td');
    id.className = 'id';
    id.textContent = obj.id;
    id.onclick = () => select(obj.id);
    const src = document.createElement('td');
    const radio = document.createElement('input');
    Object.assign(radio, { type: 'radio', name: 'source', checked: obj.id === app.model.source });
    radio.disabled = obj.shape === 'plane';
    radio.onchange = () => setSource(obj.id);
    src.appendChild(radio);
    const fixed = document.createElement('td');
    const box = document.createElement('input');
    Object.assign(box, { type: 'checkbox', checked: app.model.isFixed(obj.id) });
    box.disabled = obj.shape === 'plane' || obj.id === app.model.source;
    box.onchange = () => setFixed(obj.id, box.checked);
    fixed.appendChild(box);
    tr.append(id, src, fixed);
    body.appendChild(tr);
  }
  const s = app.model.settings;
  $('iterations').value = s.iterations;
  $('optimizer').value = s.optimizer;
  $('gradient').value = s.gradient;
  $('heatmap').checked = s.heatmap;
  $('cells-x').value = s.cells[0];
  $('cells-y').value = s.cells[1];
  updateSelectionText();
}

function updateSelectionText() {
  for (const tr of $('objects').querySelectorAll('tr[data-id]')) {
    tr.classList.toggle('selected', tr.dataset.id === app.selected);
  }
  $('select-target').classList.toggle('on', app.selected === TARGET);
  const group = groupOf(app.selected);
  const obs = observationOf(app.selected);
  const only = obs?.kind === 'position' ? ', position only' : '';
  const name = obs ? `${obs.last ? 'target' : 'observation'} (${obs.text}${only})` : app.selected;
  $('selection').textContent = group
    ? `${name}: ${group.position.toArray().map((v) => v.toFixed(3)).join(', ')}`
    : 'click an object to move it';
}

// id: an object's id, TARGET (the last observation) or '#target:<index>' (any observation).
function select(id) {
  showSetup();
  if (observationOf(id)?.last) id = TARGET;
  app.selected = id;
  const group = groupOf(id);
  if (group && (isObservation(id) || app.model.object(id).shape !== 'plane')) gizmo.attach(group);
  else gizmo.detach();
  updateSelectionText();
}

function setSource(id) {
  app.model.setSource(id);
  buildObservations();
  recolour();
  fillPanel();
}

function setFixed(id, fixed) {
  app.model.setFixed(id, fixed);
  recolour();
}

function readSettings() {
  if (!app.model?.inference) return;
  app.model.setSettings({
    iterations: Number($('iterations').value),
    optimizer: $('optimizer').value,
    gradient: $('gradient').value,
    heatmap: $('heatmap').checked,
    cells: [Number($('cells-x').value), Number($('cells-y').value)],
  });
}

function setSettings(settings) {
  app.model.setSettings(settings);
  buildStartArea();
  fillPanel();
}

for (const id of ['iterations', 'optimizer', 'gradient', 'heatmap', 'cells-x', 'cells-y']) {
  $(id).addEventListener('change', () => {
    try {
      readSettings();
      buildStartArea();
    } catch (err) {
      notify(err.message, 'error');
    }
  });
}

// ------------------------------------------------------------------ jobs
const connection = new Connection(socketUrl(), {
  onMessage: handleMessage,
  onStatus: (status) => { $('connection').classList.toggle('connected', status === 'connected'); },
});

// kind: simulate | solve | heatmap; solve becomes heatmap when the heatmap box is ticked.
function run(kind = 'solve') {
  if (!app.model) throw new Error('load a scene first');
  readSettings();
  if (kind === 'solve' && app.model.settings.heatmap) kind = 'heatmap';
  showSetup();
  const requestId = connection.submit(kind, app.model.toServerXml());
  app.requests.set(requestId, kind);
  notify(`${kind}: submitted`);
  return requestId;
}

async function fetchText(url) {
  const response = await serverFetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.text();
}

async function handleMessage(msg) {
  const job = msg.job_id && (app.jobs.get(msg.job_id) || { kind: app.requests.get(msg.request_id) });
  if (msg.job_id) app.jobs.set(msg.job_id, job);
  switch (msg.type) {
    case 'accepted':
      Object.assign(job, { kind: msg.kind, state: msg.state, requestId: msg.request_id });
      app.current = msg.job_id;
      chart.reset();
      notify(`${msg.kind} accepted${msg.queue_position ? ` (queue position ${msg.queue_position})` : ''}`);
      break;
    case 'progress':
      job.state = 'running';
      job.progress = msg;
      if (msg.job_id === app.current) chart.add(msg.iteration, msg.loss, msg.best_loss);
      break;
    case 'trajectory':
      try {
        showTrajectory(parseTrajectory(msg.csv ?? await fetchText(msg.url)));
      } catch (err) {
        notify(`trajectory: ${err.message}`, 'error');
      }
      break;
    case 'heatmap':
      try {
        showHeatmap(msg.grid ?? JSON.parse(await fetchText(msg.grid_url)));
      } catch (err) {
        notify(`heatmap: ${err.message}`, 'error');
      }
      break;
    case 'result':
      app.result = msg.result ?? JSON.parse(await fetchText(msg.url));
      if (app.result && Number.isFinite(app.result.loss)) notify(`best loss ${app.result.loss.toPrecision(3)}`);
      warnIfRunsDisagree(app.result?.posterior?.agreement);
      for (const warning of app.result?.warnings ?? []) notify(warning, 'warning');
      showResultSummary(app.result);
      break;
    case 'error':
      if (job) job.error = msg;
      notify(`${job?.kind ? `${job.kind}: ` : ''}${msg.code}: ${msg.message}`, 'error');
      break;
    case 'done':
      job.state = msg.state;
      notify(`${job.kind || 'job'} ${msg.state}`, msg.state === 'done' ? 'done' : 'error');
      if (msg.state === 'done' && (job.kind === 'heatmap' || job.kind === 'solve')) {
        await showSamples(msg.job_id);
      }
      break;
    default:
      break;
  }
}

// ------------------------------------------------------------------ results
function showTrajectory(trajectory) {
  app.trajectory = trajectory;
  if (app.path) app.path.removeFromParent();
  const source = app.model.source;
  const track = trajectory.objects[source] || Object.values(trajectory.objects)[0];
  app.path = track ? trajectorySpline(track) : null;
  if (app.path) {
    app.path.visible = $('show-path').checked;
    world.add(app.path);
  }
  gizmo.detach();
  app.selected = null;
  app.time = 0;
  app.playing = true;
  updateSelectionText();
  updatePlayback();
}

function showHeatmap(grid) {
  if (app.heatmap) app.heatmap.removeFromParent();
  app.heatmapGrid = grid;
  const area = app.model.startArea;
  const source = app.model.source;
  const surfaces = [...app.nodes].filter(([id, node]) => id !== source && node.visual)
    .map(([, node]) => node.visual);
  const topZ = area ? Math.max(area.min[2], area.max[2]) : 1;
  app.heatmap = heatmapDecal(grid, world, surfaces, topZ);
  app.heatmap.visible = $('show-heatmap').checked;
}

// The sampler's two independent runs disagree (result.json's posterior.agreement): the posterior is
// rugged and its samples, intervals and heatmap are not to be trusted.
function warnIfRunsDisagree(agreement) {
  if (!agreement || agreement.runs_agree) return;
  notify(`posterior: the sampler's independent runs disagree (R-hat up to ${agreement.max_rhat.toFixed(2)} > `
    + `${agreement.limit}); do not trust these samples`, 'warning');
}

// The result's summary in the panel: how far the answer ends from where the source was seen (the
// END, against the last observation), each observation of a tracked source, when it came to rest,
// the warnings (results.js summarizeResult).
function showResultSummary(result) {
  const list = $('result-summary');
  list.innerHTML = '';
  const lines = result ? summarizeResult(result) : [];
  for (const line of lines) {
    const li = document.createElement('li');
    li.className = line.kind;
    li.textContent = line.text;
    list.appendChild(li);
  }
  if (!lines.length) {
    const li = document.createElement('li');
    li.className = 'muted';
    li.textContent = 'no result yet';
    list.appendChild(li);
  }
}

// The posterior's samples of a done job (solve with samples, heatmap), when it drew any.
async function showSamples(jobId) {
  const response = await serverFetch(`jobs/${jobId}/posterior.csv`);
  if (!response.ok) return; // a job that drew no samples has no posterior.csv
  try {
    const samples = parsePosterior(await response.text());
    if (app.samples) app.samples.removeFromParent();
    app.samples = sampleCloud(samples);
    app.samples.visible = $('show-samples').checked;
    world.add(app.samples);
  } catch (err) {
    notify(`posterior samples: ${err.message}`, 'error');
    return;
  }
  const paths = await serverFetch(`jobs/${jobId}/posterior_paths.csv`);
  if (!paths.ok) return;
  try {
    if (app.samplePaths) app.samplePaths.removeFromParent();
    app.samplePaths = samplePaths(parsePosteriorPaths(await paths.text()));
    app.samplePaths.visible = $('show-samples').checked;
    world.add(app.samplePaths);
  } catch (err) {
    notify(`posterior paths: ${err.message}`, 'error');
  }
}

// Set-up poses back (the gizmos edit those), playback stopped.
function showSetup() {
  app.playing = false;
  if (!app.model) return;
  for (const id of app.nodes.keys()) placeFromModel(id);
  placeObservations();
  highlightObservations(null);
  updatePlayback();
}

function applyTime(t) {
  app.time = t;
  for (const [id, track] of Object.entries(app.trajectory.objects)) {
    const node = app.nodes.get(id);
    if (node && node.group.parent === world) applyPose(track, t, node.group); // not while held in VR
  }
  highlightObservations(t);
}

function updatePlayback() {
  const duration = app.trajectory?.duration || 0;
  $('play').textContent = app.playing ? 'Pause' : 'Play';
  $('scrub').value = duration ? Math.round((1000 * app.time) / duration) : 0;
  $('time').textContent = `${app.time.toFixed(2)} / ${duration.toFixed(2)} s`;
}

function play() {
  if (!app.trajectory) return;
  gizmo.detach();
  app.selected = null;
  if (app.time >= app.trajectory.duration) app.time = 0;
  app.playing = true;
  updatePlayback();
}

function pause() {
  app.playing = false;
  updatePlayback();
}

function seek(t) {
  if (!app.trajectory) return;
  gizmo.detach();
  app.playing = false;
  applyTime(Math.min(app.trajectory.duration, Math.max(0, t)));
  updatePlayback();
}

$('play').onclick = () => (app.playing ? pause() : play());
$('scrub').oninput = () => seek(((app.trajectory?.duration || 0) * Number($('scrub').value)) / 1000);
$('setup-view').onclick = () => showSetup();
$('show-heatmap').onchange = () => { if (app.heatmap) app.heatmap.visible = $('show-heatmap').checked; };
$('show-samples').onchange = () => {
  for (const shown of [app.samples, app.samplePaths]) if (shown) shown.visible = $('show-samples').checked;
};
$('show-path').onchange = () => { if (app.path) app.path.visible = $('show-path').checked; };
$('show-spheres').onchange = () => {
  const on = $('show-spheres').checked;
  for (const node of app.nodes.values()) {
    if (node.packing) {
      node.packing.visible = on;
      node.visual.visible = !on;
    }
  }
};

// ------------------------------------------------------------------ buttons, picking, files
function guard(fn) {
  return async (...args) => {
    try {
      await fn(...args);
    } catch (err) {
      notify(err.message, 'error');
    }
  };
}

$('load-scene').onclick = guard(() => loadScenePath($('scene-list').value));
$('run-simulate').onclick = guard(() => run('simulate'));
$('run-solve').onclick = guard(() => run('solve'));
$('cancel').onclick = () => { if (app.current) connection.cancel(app.current); };
$('select-target').onclick = () => select(TARGET);
$('mode-translate').onclick = () => setMode('translate');
$('mode-rotate').onclick = () => setMode('rotate');
$('export').onclick = guard(() => {
  const blob = new Blob([exportXml()], { type: 'application/xml' });
  const a = document.createElement('a');
  a.href = URL.createObjectURL(blob);
  a.download = (app.model.origin.split('/').pop() || `${app.model.name}.xml`).replace(/(\.xml)?$/, '.xml');
  a.click();
});
$('upload').onchange = guard(async () => {
  const files = new Map([...$('upload').files].map((f) => [f.name, f]));
  const xml = [...files.values()].find((f) => f.name.toLowerCase().endsWith('.xml'));
  if (!xml) throw new Error('choose a scene .xml file (with its meshes)');
  await loadScene(await xml.text(), '', files);
});

function setMode(mode) {
  gizmo.setMode(mode);
  $('mode-translate').classList.toggle('on', mode === 'translate');
  $('mode-rotate').classList.toggle('on', mode === 'rotate');
}

function exportXml() {
  readSettings();
  return app.model.toXml();
}

const down = new THREE.Vector2();
renderer.domElement.addEventListener('pointerdown', (e) => down.set(e.clientX, e.clientY));
renderer.domElement.addEventListener('pointerup', (e) => {
  if (!app.model || gizmo.dragging || down.distanceTo(new THREE.Vector2(e.clientX, e.clientY)) > 4) return;
  const rect = renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((e.clientX - rect.left) / rect.width) * 2 - 1,
    -((e.clientY - rect.top) / rect.height) * 2 + 1);
  const ray = new THREE.Raycaster();
  ray.setFromCamera(ndc, camera);
  const pickable = [...app.nodes.values()].map((n) => n.group);
  for (const obs of app.observations) if (obs.group.visible) pickable.push(obs.group);
  const hit = ray.intersectObjects(pickable, true).find((h) => h.object.visible &&
    (isObservation(h.object.userData.objectId) || app.model.object(h.object.userData.objectId)?.shape !== 'plane'));
  if (hit) select(hit.object.userData.objectId);
});
window.addEventListener('keydown', (e) => {
  if (e.target.tagName === 'INPUT' || e.target.tagName === 'SELECT') return;
  if (e.key === 'w') setMode('translate');
  if (e.key === 'e') setMode('rotate');
  if (e.key === ' ') (app.playing ? pause() : play());
  if (e.key === 'Escape') { gizmo.detach(); app.selected = null; updateSelectionText(); }
});

async function listScenes() {
  const response = await serverFetch('scenes');
  const { scenes } = await response.json();
  $('scene-list').innerHTML = '';
  for (const path of scenes) $('scene-list').append(new Option(path, path));
  return scenes;
}

// ------------------------------------------------------------------ VR and the frame loop
const vr = setupVR({
  renderer, scene, world,
  grabbable: () => {
    const groups = [...app.nodes].filter(([id]) => !app.model.isFixed(id)).map(([, n]) => n.group);
    for (const obs of app.observations) if (obs.group.visible) groups.push(obs.group);
    return groups;
  },
  onGrab: () => showSetup(),
  onRelease: (group) => poseEdited(group),
  onSolve: () => run('solve'),
});

const timer = new THREE.Timer();
renderer.setAnimationLoop(() => {
  timer.update();
  const dt = Math.min(0.1, timer.getDelta());
  if (app.playing && app.trajectory) {
    let t = app.time + dt;
    if (t > app.trajectory.duration + 0.25) t = 0; // loop, with a short rest on the last pose
    applyTime(t);
    updatePlayback();
  }
  vr.update();
  placeLabels();
  renderer.render(scene, camera);
});

// ------------------------------------------------------------------ test hooks
function positions() {
  const out = {};
  for (const [id, node] of app.nodes) {
    out[id] = world.worldToLocal(node.group.getWorldPosition(new THREE.Vector3())).toArray();
  }
  return out;
}

window.dejaview = {
  state: () => ({
    scene: app.model?.name ?? null,
    origin: app.model?.origin ?? null,
    objects: app.model ? app.model.objects.map((o) => o.id) : [],
    meshesLoaded: [...app.nodes.values()].filter((n) => n.visual).length,
    robotLinks: Object.fromEntries([...app.nodes].filter(([, n]) => n.visual?.userData.robotLinks)
      .map(([id, n]) => [id, n.visual.userData.robotLinks])),
    packings: Object.fromEntries([...app.nodes].filter(([, n]) => n.packing)
      .map(([id, n]) => [id, { spheres: n.packing.count, visible: n.packing.visible }])),
    source: app.model?.source ?? null,
    target: app.model?.target ?? null,
    targets: app.model?.targets ?? [],
    // what is drawn for each observation: kind 'pose' (a ghost) or 'position' (a marker), its label
    observations: app.observations.map((o) => ({
      index: o.index, id: o.id, kind: o.kind, label: o.text, last: o.last, highlighted: o.highlighted,
      shown: Boolean(o.group.parent && o.group.visible && o.label.parent && o.label.visible),
      position: world.worldToLocal(o.group.getWorldPosition(new THREE.Vector3())).toArray(),
    })),
    resultSummary: [...$('result-summary').children].filter((li) => li.className !== 'muted')
      .map((li) => ({ kind: li.className, text: li.textContent })),
    selected: app.selected,
    gizmoAttached: Boolean(gizmo.object),
    positions: positions(),
    setup: Object.fromEntries((app.model?.objects || []).map((o) => [o.id, o.position])),
    animation: { time: app.time, duration: app.trajectory?.duration ?? 0, playing: app.playing },
    trajectoryShown: Boolean(app.path?.parent && app.path.visible),
    trajectoryObjects: app.trajectory ? Object.keys(app.trajectory.objects) : [],
    heatmapShown: Boolean(app.heatmap?.parent && app.heatmap.visible),
    heatmapCells: app.heatmapGrid?.cells ?? null,
    samplesShown: Boolean(app.samples?.parent && app.samples.visible),
    sampleCount: app.samples ? app.samples.geometry.attributes.position.count : 0,
    samplePaths: app.samplePaths?.parent && app.samplePaths.visible ? app.samplePaths.children.length : 0,
    jobs: [...app.jobs].map(([id, j]) => ({ id, kind: j.kind, state: j.state, error: j.error?.code })),
    loss: chart.points,
    result: app.result,
    notifications: app.notifications,
    connected: connection.connected,
    settings: app.model?.inference ? app.model.settings : null,
    xr: vr.state(),
  }),
  listScenes, loadScenePath, select, setSource, setFixed, setSettings, run, exportXml, play, pause, seek,
  showSetup,
  loadSceneXml: (text, origin = '') => loadScene(text, origin, null),
  // the scene's observations: edit one ({position, orientation, time, moving}; null removes), add, remove
  setObservation: (index, fields) => { app.model.setObservation(index, fields); buildObservations(); },
  addObservation: (fields) => { const i = app.model.addObservation(fields); buildObservations(); return i; },
  removeObservation: (index) => { app.model.removeObservation(index); buildObservations(); },
  setPose: (id, position, orientation) => {
    showSetup();
    const group = groupOf(id);
    group.position.set(...position);
    if (orientation) group.quaternion.copy(toQuat(orientation));
    poseEdited(group);
  },
  // where an object is on the page, for real mouse input in tests: {x, y} in CSS pixels
  screenPoint: (id, offset = [0, 0, 0]) => {
    const group = groupOf(id);
    const p = world.localToWorld(group.position.clone().add(new THREE.Vector3(...offset))).project(camera);
    const rect = renderer.domElement.getBoundingClientRect();
    return { x: rect.left + ((p.x + 1) / 2) * rect.width, y: rect.top + ((1 - p.y) / 2) * rect.height };
  },
  three: { THREE, renderer, scene, camera, world, gizmo },
};

listScenes().catch((err) => notify(`scene list: ${err.message}`, 'error'));
