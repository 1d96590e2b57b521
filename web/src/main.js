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
  addTimedTarget, deleteTarget, fillObjects, fillPanel, fillTargets, readSettings, setupPanel,
} from './panel.js';
import {
  clearPosterior, setupPosteriorView, showPosteriorSummary, showRegion, showRegionFromSamples,
} from './posterior-view.js';
import { removeObject, setMeshes, spawnObject } from './spawn.js';
import {
  TARGET, groupOf, isObservation, observationOf, poseEdited, updateSelectionText,
} from './selection.js';
import { camera, gizmo, renderer, scene, world } from './stage.js';
import { $, app, notify } from './state.js';
import { installTestHooks } from './test-hooks.js';
import { menuStatus, observationIdOf, pressMenu } from './vr-actions.js';
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
  showSceneName();
  notify(`loaded ${model.name}`);
  return model.objects.map((o) => o.id);
}

function showSceneName() {
  const { model } = app;
  $('scene-name').textContent = `${model.name}${model.origin ? ` (${model.origin})` : ''}: ${model.objects.length} objects`;
}

async function loadScenePath(path) {
  const response = await serverFetch(`files/${path.split('/').map(encodeURIComponent).join('/')}`);
  if (!response.ok) throw new Error(`${path}: HTTP ${response.status}`);
  return loadScene(await response.text(), path);
}

// ------------------------------------------------------------------ panel (panel.js)
// id: an object's id, TARGET (the last observation) or '#target:<index>' (any observation).
function select(id) {
  showSetup();
  if (observationOf(id)?.last) id = TARGET;
  app.selected = id;
  const group = groupOf(id);
  // in VR the controllers move things: no gizmo there
  if (group && !renderer.xr.isPresenting && (isObservation(id) || app.model.object(id).shape !== 'plane')) {
    gizmo.attach(group);
  }
  else gizmo.detach();
  updateSelectionText();
  fillTargets();
}

function setSource(id) {
  if (app.model.setSource(id)) {
    buildStartArea();
    notify(`the start area moved to ${id}: it did not hold its set-up position`, 'warning');
  }
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

function setSettings(settings) {
  app.model.setSettings(settings);
  buildStartArea();
  fillPanel();
}

function setBelief(values) {
  app.model.setBelief(values);
  live.sceneChanged();
  fillPanel();
}

setupPanel({
  select, setSource, setFixed,
  changed: () => live.sceneChanged(),
  observationsChanged: () => {
    showSetup();
    buildObservations();
    // the gizmo follows the selected observation's new group (or lets go of one deleted)
    const group = isObservation(app.selected) ? groupOf(app.selected) : null;
    if (group && !renderer.xr.isPresenting) gizmo.attach(group);
    else if (isObservation(app.selected)) { gizmo.detach(); app.selected = null; }
    updateSelectionText();
  },
  settingsChanged: () => buildStartArea(),
});

async function spawn(kind, position) {
  const id = await spawnObject(kind, position);
  live.sceneChanged();
  fillObjects();
  showSceneName();
  select(id);
  notify(`added ${id}`);
  return id;
}

function removeSelected(id = app.selected) {
  if (!id || isObservation(id)) throw new Error('select an object to remove (a target: its × in the table)');
  gizmo.detach();
  app.selected = null;
  removeObject(id);
  live.sceneChanged();
  fillObjects();
  showSceneName();
  updateSelectionText();
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
  clearPosterior();
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
      if (app.modeRequests.has(msg.request_id)) { // a mode's past: the solve's chart and results stay
        job.mode = app.modeRequests.get(msg.request_id);
        break;
      }
      app.current = msg.job_id;
      chart.reset();
      notify(`${msg.kind} accepted${msg.queue_position ? ` (queue position ${msg.queue_position})` : ''}`);
      break;
    case 'progress':
      job.state = 'running';
      job.progress = msg;
      if (msg.job_id !== app.current) break;
      // the sampler's progress is no loss curve (its numbers are the search's answer): a note
      if (msg.phase === 'sample') chart.setNote(`sampling: ${Math.round(100 * (msg.fraction ?? 0))} %`);
      else chart.add(msg.iteration, msg.loss, msg.best_loss);
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
        const grid = msg.grid ?? JSON.parse(await fetchText(msg.grid_url));
        showHeatmap(grid);
        showRegion(grid, 'heatmap');
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
      showPosteriorSummary(app.result);
      break;
    case 'error':
      if (job) job.error = msg;
      notify(`${job?.kind ? `${job.kind}: ` : ''}${msg.code}: ${msg.message}`, 'error');
      break;
    case 'done':
      job.state = msg.state;
      if (msg.job_id === app.current) chart.setNote('');
      notify(`${job.kind || 'job'} ${msg.state}`, msg.state === 'done' ? 'done' : 'error');
      if (msg.state === 'done' && (job.kind === 'heatmap' || job.kind === 'solve')) {
        const samples = await showSamples(msg.job_id);
        if (samples && app.region?.from !== 'heatmap') showRegionFromSamples(samples);
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
$('spawn').onclick = guard(() => spawn($('spawn-kind').value));
$('remove-object').onclick = guard(() => removeSelected());
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

// A mode of the posterior (result.json's posterior.modes, or the search's): its past, played as the
// answer's is (a simulate job of the scene with the source started there); the solve's results stay.
function playMode(mode, k) {
  const requestId = connection.submit('simulate', app.model.toServerXml(mode.initial_state));
  app.requests.set(requestId, 'simulate');
  app.modeRequests.set(requestId, k);
  app.modePlaying = k;
  for (const b of document.querySelectorAll('#modes button')) b.classList.toggle('on', b.dataset.mode === String(k));
  notify(`playing past ${k + 1}: simulating it`);
  return requestId;
}
setupPosteriorView({ playMode });

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
  const { scenes, meshes } = await response.json();
  setMeshes(meshes);
  $('scene-list').innerHTML = '';
  for (const path of scenes) $('scene-list').append(new Option(path, path));
  return scenes;
}

// ------------------------------------------------------------------ VR and the frame loop
const vr = setupVR({
  renderer, scene, world,
  // fixed objects are picked (selected, for the menu's "fixed" and "source") but not moved
  grabbable: () => {
    const groups = [...app.nodes].filter(([id]) => app.model.object(id).shape !== 'plane' && !app.model.object(id).robot)
      .map(([, n]) => n.group);
    for (const obs of app.observations) if (obs.group.visible) groups.push(obs.group);
    return groups;
  },
  movable: (group) => group.userData.observation !== undefined || !app.model.isFixed(group.userData.objectId),
  onGrab: (group) => {
    showSetup();
    app.selected = group.userData.observation !== undefined ? observationIdOf(group) : group.userData.objectId;
    updateSelectionText();
    menuStatus(vr.menu);
  },
  onRelease: (group) => { poseEdited(group); live.moved(group); fillTargets(); menuStatus(vr.menu); },
  // the live answer follows the target while it is carried (one request in flight, the newest pose)
  onCarry: (group) => { if (group === groupOf(TARGET)) live.moved(group); },
  onSolve: () => run('solve'),
  onMenu: (name, at) => pressMenu(name, at, menuActions).then(() => menuStatus(vr.menu), (err) => {
    notify(err.message, 'error');
    vr.menu.setStatus(err.message);
  }),
});
const menuActions = {
  addTimedTarget, deleteTarget, spawn, setSource, setFixed, removeSelected, run,
  changed: () => live.sceneChanged(),
  observationsChanged: () => { buildObservations(); fillTargets(); },
  objectsChanged: () => fillObjects(),
};

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
  live.frame();
});

installTestHooks({
  chart, connection, vr, live,
  actions: {
    listScenes, loadScenePath, select, setSource, setFixed, setSettings, setBelief, run, exportXml, trainModel,
    spawn, removeObject: removeSelected, addTimedTarget, deleteTarget, playMode,
    loadSceneXml: (text, origin = '') => loadScene(text, origin, null),
  },
});

listScenes().catch((err) => notify(`scene list: ${err.message}`, 'error'));
