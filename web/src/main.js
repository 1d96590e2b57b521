// The DejaView web viewer: load a scene, set up the problem, run jobs on the service, watch results.
// The stage (stage.js), the scene (scene-view.js), selections (selection.js), results and playback
// (result-view.js) are modules; this one holds the panel, the jobs, the inputs and the frame loop.
// Test hooks: window.dejaview (test-hooks.js).
import * as THREE from 'three';

import { LossChart } from './chart.js';
import { Connection, serverFetch, socketUrl } from './connection.js';
import { Live } from './live.js';
import { parseTrajectory } from './results.js';
import {
  applyTime, clearResults, pause, play, showHeatmap, showResultSummary, showSamples, showSetup, showTrajectory,
  updatePlayback, warnIfRunsDisagree,
} from './result-view.js';
import {
  buildObject, buildObservations, buildStartArea, fitCamera, placeLabels, recolour, removeObservations,
} from './scene-view.js';
import { SceneModel } from './scene-xml.js';
import {
  TARGET, groupOf, isObservation, observationOf, poseEdited, updateSelectionText,
} from './selection.js';
import { camera, gizmo, renderer, scene, world } from './stage.js';
import { $, app, notify } from './state.js';
import { installTestHooks } from './test-hooks.js';
import { setupVR } from './vr.js';

gizmo.addEventListener('objectChange', () => {
  poseEdited(gizmo.object);
  live.moved(gizmo.object);
});

const chart = new LossChart($('loss'));
chart.draw();

// ------------------------------------------------------------------ loading a scene
function clearScene() {
  gizmo.detach();
  clearResults();
  app.startArea?.removeFromParent();
  for (const node of app.nodes.values()) world.remove(node.group);
  removeObservations();
  app.nodes.clear();
  app.selected = null;
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
  live.sceneChanged();
  live.clear();
  live.moved(null);
  $('scene-name').textContent = `${model.name}${origin ? ` (${origin})` : ''}: ${model.objects.length} objects`;
  notify(`loaded ${model.name}`);
  return model.objects.map((o) => o.id);
}

async function loadScenePath(path) {
  const response = await serverFetch(`files/${path.split('/').map(encodeURIComponent).join('/')}`);
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status}`);
  return loadScene(await response.text(), path);
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
  live.sceneChanged();
  buildObservations();
  recolour();
  fillPanel();
}

function setFixed(id, fixed) {
  app.model.setFixed(id, fixed);
  live.sceneChanged();
  recolour();
}

function readSettings() {
  if (!app.model?.inference) return;
  live.sceneChanged();
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
const live = new Live(connection);

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
  if (live.handle(msg)) return;
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
      if (msg.state === 'done' && job.kind === 'train') live.moved(null); // its model answers now
      break;
    default:
      break;
  }
}


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
$('live').onchange = () => live.setEnabled($('live').checked);
$('train').onclick = guard(() => trainModel());
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

// A train job for the scene as it is now: the server's model of it, which live answers come from.
function trainModel() {
  if (!app.model) throw new Error('load a scene first');
  readSettings();
  const requestId = connection.submit('train', app.model.toServerXml());
  app.requests.set(requestId, 'train');
  notify('train: submitted');
  return requestId;
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
  onRelease: (group) => { poseEdited(group); live.moved(group); },
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

installTestHooks({
  chart, connection, vr, live,
  actions: {
    listScenes, loadScenePath, select, setSource, setFixed, setSettings, run, exportXml, trainModel,
    loadSceneXml: (text, origin = '') => loadScene(text, origin, null),
  },
});

listScenes().catch((err) => notify(`scene list: ${err.message}`, 'error'));
