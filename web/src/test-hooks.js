// Test hooks: window.dejaview, the viewer's state as plain data and the actions the browser tests
// drive (state(), loadScenePath(), setPose(), run(), ...).
import * as THREE from 'three';

import { pause, play, seek, showSetup, showTrajectory } from './result-view.js';
import { parseTrajectory } from './results.js';
import { buildObservations } from './scene-view.js';
import { groupOf, poseEdited, toQuat } from './selection.js';
import { camera, gizmo, renderer, scene, world } from './stage.js';
import { $, app } from './state.js';

function positions() {
  const out = {};
  for (const [id, node] of app.nodes) {
    out[id] = world.worldToLocal(node.group.getWorldPosition(new THREE.Vector3())).toArray();
  }
  return out;
}

// chart, connection, vr, live: the loss chart, the service connection, the VR state and the live
// answers (live.js) main.js made;
// actions: main.js's functions the tests call (listScenes, loadScenePath, loadSceneXml, select, ...).
export function installTestHooks({ chart, connection, vr, live, actions }) {
  window.dejaview = {
    state: () => ({
      scene: app.model?.name ?? null,
      origin: app.model?.origin ?? null,
      objects: app.model ? app.model.objects.map((o) => o.id) : [],
      meshesLoaded: [...app.nodes.values()].filter((n) => n.visual).length,
      robotLinks: Object.fromEntries([...app.nodes].filter(([, n]) => n.visual?.userData.robotLinks)
        .map(([id, n]) => [id, n.visual.userData.robotLinks])),
      // each robot link's position in the world (a moving robot's: where playback put it)
      linkPositions: Object.fromEntries([...app.nodes.values()].filter((n) => n.visual?.userData.robotLinks)
        .flatMap((n) => n.visual.children.map((part) => [
          part.name, world.worldToLocal(part.getWorldPosition(new THREE.Vector3())).toArray()]))),
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
      belief: app.model?.inference ? app.model.belief : null,
      // the 90 % credible region on the floor, and the Result panel's posterior (posterior-view.js)
      region: app.region ? { shown: Boolean(app.region.group.parent && app.region.group.visible),
        from: app.region.from, mass: app.region.mass, cells: app.region.cells, area: app.region.area } : null,
      intervals: [...document.querySelectorAll('#intervals tr[data-parameter]')]
        .map((tr) => ({ parameter: tr.dataset.parameter, text: tr.textContent })),
      modes: [...document.querySelectorAll('#modes button')].map((b) => b.textContent),
      agreement: document.querySelector('#posterior-view .agreement')?.textContent ?? null,
      physics: [...document.querySelectorAll('#physics li')].map((li) => li.textContent),
      modePlaying: app.modePlaying,
      xr: vr.state(),
      live: live.state(),
    }),
    ...actions, play, pause, seek, showSetup,
    // where to hold a controller to press a VR menu button: {position, quaternion} (XR frame)
    vrMenuAim: (name) => vr.menu.aim(name),
    // a trajectory.csv shown as a job's would be (playback without running a job)
    showTrajectoryCsv: (csv) => showTrajectory(parseTrajectory(csv)),
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
}
