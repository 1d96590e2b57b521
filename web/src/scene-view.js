// The scene in three: each object (mesh, primitive, robot links, sphere packing) in its colour, the
// start area, the observations with their labels, and the camera framed on them.
import * as THREE from 'three';

import { serverFetch } from './connection.js';
import { loadMesh, parseSpheres, primitiveGeometry, spheresMesh } from './geometry.js';
import {
  buildObservation, highlightObservation, observationLine, updateObservationLine,
} from './observations.js';
import { applyPose, observationTimes } from './results.js';
import { observationId, toQuat } from './selection.js';
import { camera, orbit, renderer, world } from './stage.js';
import { $, app, notify } from './state.js';

// playback lights an observation up from a little before its time until a little after (at most
// halfway to the next observation's time)
const HIGHLIGHT_BEFORE_S = 0.03;
const HIGHLIGHT_AFTER_S = 0.25;
const PALETTE = [0x5b8fd9, 0x2ca02c, 0x9467bd, 0x17becf, 0xbcbd22, 0xe377c2, 0x8c564b];
const SOURCE_COLOUR = 0xff7f0e;
const FIXED_COLOUR = 0x8a8f98;

export function placeFromModel(id) {
  const node = app.nodes.get(id);
  const obj = app.model.object(id);
  node.group.position.set(...obj.position);
  node.group.quaternion.copy(toQuat(obj.orientation));
}

// Every observation at its observed pose (a position-only one unturned).
export function placeObservations() {
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

export function recolour() {
  for (const [id, node] of app.nodes) {
    node.visual?.traverse((m) => { if (m.isMesh) m.material.color.setHex(colourOf(id)); });
  }
}

export async function buildObject(obj) {
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
    if (link.motion) part.userData.motion = link.motion; // a moving robot: its poses over time
    group.add(part);
    group.userData.robotLinks.push(link.name);
  }
  return group;
}

// Moving robots' links where they are at time t (s; 0: the set-up view), from the poses the server
// sampled (robot-links' motion), as the trajectory's objects are played.
export function poseRobots(t) {
  for (const node of app.nodes.values()) {
    if (!node.visual?.userData.robotLinks) continue;
    for (const part of node.visual.children) {
      if (part.userData.motion) applyPose(part.userData.motion, t, part);
    }
  }
}

// The start area (a box that bounds the initial position) as a wire box; a flat area as a square.
export function buildStartArea() {
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
export function buildObservations() {
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

export function removeObservations() {
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
export function placeLabels() {
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
export function highlightObservations(t) {
  const times = t == null ? [] : observationTimes(app.model?.targets ?? [], app.result, app.trajectory?.duration);
  const sorted = times.filter((x) => x != null).sort((a, b) => a - b);
  for (const obs of app.observations) {
    const at = times[obs.index];
    const next = sorted.find((x) => x > at);
    const after = next === undefined ? HIGHLIGHT_AFTER_S : Math.min(HIGHLIGHT_AFTER_S, (next - at) / 2);
    highlightObservation(obs, at != null && t >= at - HIGHLIGHT_BEFORE_S && t <= at + after);
  }
}

export function fitCamera() {
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
