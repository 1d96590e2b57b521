// The set-up panel: the objects table (source, fixed), the inference's belief (prior, observation
// noise, physics prior, samples), the observations' table (timed targets: add, time, at rest or
// moving, delete), and the seed's optimiser settings under "advanced". Every input writes the scene
// model at once (scene-xml.js, scene-belief.js), so Export and a job's scene_xml hold what it shows.
import * as THREE from 'three';

import { applyPose } from './results.js';
import { TARGET, observationId } from './selection.js';
import { $, app, notify } from './state.js';

// input id -> [belief group, key]
const BELIEF_INPUTS = {
  'prior-speed': ['prior', 'speed'],
  'prior-spin': ['prior', 'spin'],
  'prior-tilt': ['prior', 'tilt'],
  'obs-sigma': ['observation', 'sigma'],
  'obs-angle-sigma': ['observation', 'angleSigma'],
  'obs-rest-speed': ['observation', 'restSpeed'],
  'obs-rest-spin': ['observation', 'restSpin'],
  'phys-friction': ['physicsPrior', 'friction'],
  'phys-restitution': ['physicsPrior', 'restitution'],
  'phys-stiffness': ['physicsPrior', 'stiffness'],
  'mu-friction': ['modelUncertainty', 'friction'],
  'mu-restitution': ['modelUncertainty', 'restitution'],
};
const SETTINGS_INPUTS = ['iterations', 'optimizer', 'gradient', 'heatmap', 'cells-x', 'cells-y'];

// hooks: {select(id), setSource(id), setFixed(id, fixed), changed() (the scene changed: live
// answers resend it), observationsChanged() (redraw them), settingsChanged() (the start area)}
let hooks = null;

export function setupPanel(h) {
  hooks = h;
  for (const id of Object.keys(BELIEF_INPUTS)) $(id).addEventListener('change', () => guarded(readBelief));
  $('samples').addEventListener('change', () => guarded(readBelief));
  for (const id of SETTINGS_INPUTS) {
    $(id).addEventListener('change', () => guarded(() => settingsInput(id)));
  }
  $('add-target').onclick = () => guarded(() => addTimedTarget());
}

function guarded(fn) {
  try {
    fn();
  } catch (err) {
    notify(err.message, 'error');
    if (app.model) fillInference(); // back to what the scene holds
  }
}

export function fillPanel() {
  fillObjects();
  fillInference();
}

export function fillObjects() {
  const body = $('objects').querySelector('tbody');
  body.innerHTML = '';
  for (const obj of app.model.objects) {
    const tr = document.createElement('tr');
    tr.dataset.id = obj.id;
    const id = document.createElement('td');
    id.className = 'id';
    id.textContent = obj.id;
    id.onclick = () => hooks.select(obj.id);
    const src = document.createElement('td');
    const radio = document.createElement('input');
    Object.assign(radio, { type: 'radio', name: 'source', checked: obj.id === app.model.source });
    radio.disabled = obj.shape === 'plane' || Boolean(obj.robot);
    radio.setAttribute('aria-label', `${obj.id} is the source`);
    radio.onchange = () => hooks.setSource(obj.id);
    src.appendChild(radio);
    const fixed = document.createElement('td');
    const box = document.createElement('input');
    Object.assign(box, { type: 'checkbox', checked: app.model.isFixed(obj.id) });
    box.disabled = obj.shape === 'plane' || obj.id === app.model.source;
    box.setAttribute('aria-label', `${obj.id} is fixed`);
    box.onchange = () => hooks.setFixed(obj.id, box.checked);
    fixed.appendChild(box);
    tr.append(id, src, fixed);
    body.appendChild(tr);
  }
}

const show = (v) => (v === null || v === undefined ? '' : String(v));

export function fillInference() {
  const has = Boolean(app.model?.inference);
  $('add-target').disabled = !has;
  fillTargets();
  if (!has) { // a scene without <inference>: nothing to show until a source is chosen
    for (const id of [...Object.keys(BELIEF_INPUTS), 'samples']) $(id).value = '';
    return;
  }
  const belief = app.model.belief;
  for (const [id, [group, key]] of Object.entries(BELIEF_INPUTS)) $(id).value = show(belief[group][key]);
  $('samples').value = belief.samples ? String(belief.samples) : '';
  const s = app.model.settings;
  $('iterations').value = show(s.iterations);
  $('optimizer').value = s.optimizer;
  $('gradient').value = s.gradient;
  $('heatmap').checked = s.heatmap;
  $('cells-x').value = s.cells[0];
  $('cells-y').value = s.cells[1];
}

function readBelief() {
  if (!app.model) return;
  if (!app.model.inference) throw new Error('choose a source first: the scene has no <inference>');
  const values = {};
  for (const [id, [group, key]] of Object.entries(BELIEF_INPUTS)) {
    (values[group] ??= {})[key] = $(id).value.trim() === '' ? null : Number($(id).value);
  }
  values.samples = $('samples').value.trim() === '' ? 0 : Number($('samples').value);
  app.model.setBelief(values);
  hooks.changed();
  warnSamplesNeedTheSearch();
}

// Samples are drawn around the default search's modes: a local optimiser's solve would fail on them.
function warnSamplesNeedTheSearch() {
  if (app.model.belief.samples > 0 && app.model.settings.optimizer !== 'auto') {
    notify(`samples need the default search: set "advanced" > optimizer back to the default search `
      + `(now ${app.model.settings.optimizer})`, 'warning');
  }
}

export function readSettings() {
  if (!app.model?.inference) return;
  hooks.changed();
  app.model.setSettings({
    iterations: $('iterations').value.trim() === '' ? '' : Number($('iterations').value),
    optimizer: $('optimizer').value,
    gradient: $('gradient').value,
    heatmap: $('heatmap').checked,
    cells: [Number($('cells-x').value), Number($('cells-y').value)],
  });
}

function settingsInput(id) {
  readSettings();
  hooks.settingsChanged();
  if (id === 'optimizer') warnSamplesNeedTheSearch();
}

// ------------------------------------------------------------------ the observations' table
// Each <target>: "end" or its time, how it was seen, a delete button. An untimed target was seen
// at rest (the default) or moving (moving="true"); a timed one was seen at that moment, moving or
// not (the default) or lying still then (moving="false").
const HOW = {
  end: [['rest', 'at rest'], ['moving', 'moving']],
  timed: [['any', 'moving or not'], ['rest', 'lying still']],
};

function howOf(target) {
  if (target.time == null) return target.atRest ? 'rest' : 'moving';
  return target.moving === false ? 'rest' : 'any';
}

export function fillTargets() {
  const body = $('targets').querySelector('tbody');
  body.innerHTML = '';
  const targets = app.model?.targets ?? [];
  targets.forEach((target) => {
    const tr = document.createElement('tr');
    tr.dataset.index = String(target.index);
    tr.className = target.last ? 'last' : 'earlier';
    tr.classList.toggle('selected', observationId(target) === app.selected);
    const seen = document.createElement('td');
    seen.className = 'seen';
    seen.textContent = target.last ? 'target' : `#${target.index + 1}`;
    seen.title = `${target.orientation ? 'a pose' : 'a position alone'} was seen; click to select it, then move it `
      + 'with the gizmo (or grab it in VR)';
    seen.onclick = () => hooks.select(observationId(target));
    const time = document.createElement('td');
    const input = document.createElement('input');
    Object.assign(input, { type: 'number', min: '0', step: 'any', className: 'time', placeholder: 'end',
      value: target.time == null ? '' : String(target.time) });
    input.setAttribute('aria-label', `time of observation ${target.index + 1} (s)`);
    input.onchange = () => guarded(() => {
      const t = input.value.trim() === '' ? null : Number(input.value);
      if (t !== null && !(Number.isFinite(t) && t >= 0)) throw new Error(`a target's time is in seconds >= 0, got ${input.value}`);
      app.model.setObservation(target.index, { time: t, ...(t === null ? { moving: null } : {}) });
      observationsChanged();
    });
    time.appendChild(input);
    const how = document.createElement('td');
    const select = document.createElement('select');
    select.setAttribute('aria-label', `how observation ${target.index + 1} was seen`);
    for (const [value, label] of HOW[target.time == null ? 'end' : 'timed']) select.append(new Option(label, value));
    select.value = howOf(target);
    select.onchange = () => guarded(() => {
      setHow(target, select.value);
      observationsChanged();
    });
    how.appendChild(select);
    const del = document.createElement('td');
    const button = document.createElement('button');
    button.textContent = '×';
    button.title = 'delete this observation';
    button.disabled = targets.length <= 1;
    button.onclick = () => guarded(() => deleteTarget(target.index));
    del.appendChild(button);
    const pose = document.createElement('td');
    const check = document.createElement('input');
    Object.assign(check, { type: 'checkbox', checked: Boolean(target.orientation), className: 'pose',
      title: 'the orientation was seen too (a pose); unticked: the position alone' });
    check.setAttribute('aria-label', `observation ${target.index + 1} saw the orientation`);
    check.onchange = () => guarded(() => {
      app.model.setObservation(target.index, { orientation: check.checked ? orientationAt(target) : null });
      observationsChanged();
    });
    pose.appendChild(check);
    tr.append(seen, time, how, pose, del);
    body.appendChild(tr);
  });
}

// The source's orientation when it was seen: on the answer's path at the target's time where a
// trajectory is shown, else its set-up orientation (w x y z).
function orientationAt(target) {
  const track = app.trajectory?.objects[app.model.source];
  if (track) {
    const probe = new THREE.Object3D();
    applyPose(track, target.time ?? app.trajectory.duration, probe);
    const q = probe.quaternion;
    return [q.w, q.x, q.y, q.z];
  }
  return app.model.object(app.model.source).orientation;
}

function setHow(target, how) {
  const velocities = Boolean(target.linearVelocity || target.angularVelocity);
  if (target.time == null) {
    // at rest is the default of an untimed target without velocities: the attribute stays out
    app.model.setObservation(target.index, { moving: how === 'moving' ? true : (velocities ? false : null) });
  } else {
    app.model.setObservation(target.index, { moving: how === 'rest' ? false : null });
  }
}

function observationsChanged() {
  hooks.changed();
  hooks.observationsChanged();
  fillTargets();
}

// A new <target time=...> (position only): at the playback time on the answer's path where a
// trajectory is shown, else halfway through the scene, between the source's set-up position and
// the last observation. Returns its index.
export function addTimedTarget(time = null, position = null) {
  if (!app.model?.inference) throw new Error('choose a source first: the scene has no <inference>');
  const source = app.model.source;
  const track = app.trajectory?.objects[source];
  let t = time;
  if (t == null) t = track && app.time > 0 ? app.time : app.model.duration / 2;
  t = Number(t.toFixed(3));
  let at = position;
  if (!at && track) {
    const probe = new THREE.Object3D();
    applyPose(track, t, probe);
    at = probe.position.toArray();
  }
  if (!at) {
    const from = app.model.object(source).position;
    const to = app.model.target?.position ?? from;
    const u = Math.min(1, t / app.model.duration);
    at = from.map((v, i) => v + (to[i] - v) * u);
  }
  const index = app.model.addObservation({ position: at, time: t });
  observationsChanged();
  hooks.select(observationId({ index, last: app.model.targets[index].last }));
  return index;
}

export function deleteTarget(index) {
  app.model.removeObservation(index);
  if (app.selected && app.selected !== TARGET) app.selected = null;
  observationsChanged();
}
