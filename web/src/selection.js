// What a selection id names (an object, the target, another observation), the group it moves, and
// poses between the scene model (w x y z) and three (x y z w).
import * as THREE from 'three';

import { updateObservationLine } from './observations.js';
import { $, app } from './state.js';

export const TARGET = '#target'; // selection id of the target ghost (the last observation)
const OBSERVATION = '#target:'; // selection ids of the other observations: '#target:<index>'

export const toQuat = ([w, x, y, z]) => new THREE.Quaternion(x, y, z, w).normalize();
export const fromQuat = (q) => [q.w, q.x, q.y, q.z];

// The selection id of an observation: the last one is the target, TARGET.
export const observationId = (target) => (target.last ? TARGET : `${OBSERVATION}${target.index}`);
export const isObservation = (id) => typeof id === 'string' && (id === TARGET || id.startsWith(OBSERVATION));

export function observationOf(id) {
  if (id === TARGET) return app.observations.find((o) => o.last) || null;
  if (isObservation(id)) return app.observations.find((o) => o.index === Number(id.slice(OBSERVATION.length))) || null;
  return null;
}

// The group a selection id moves: an object's, or an observation's.
export function groupOf(id) {
  return isObservation(id) ? observationOf(id)?.group ?? null : app.nodes.get(id)?.group ?? null;
}

// A gizmo or a VR controller moved `group`: write its pose into the scene.
export function poseEdited(group) {
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

export function updateSelectionText() {
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
