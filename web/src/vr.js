// WebXR: the "Enter VR" button, and two controllers that grab and move objects (trigger) and
// start a solve (squeeze); a menu above the left controller (vr-menu.js) whose buttons the
// trigger presses: timed targets, new objects, source and fixed, solve.
import * as THREE from 'three';
import { VRButton } from 'three/addons/webxr/VRButton.js';

import { VRMenu } from './vr-menu.js';

const AHEAD = 0.5; // m: where the menu's "add" buttons put a target or an object, in front of the eyes

// onMenu(name, at): a menu button pressed, at: half a metre in front of the eyes, in the scene (z up).
// grabbable(): the groups a ray may pick; movable(group): whether a picked one is carried (else it is
// only selected: onGrab without a release); onCarry(group): each frame a carried group has moved in.
export function setupVR({ renderer, scene, world, grabbable, movable, onGrab, onRelease, onSolve, onMenu,
  onCarry = () => {} }) {
  renderer.xr.enabled = true;
  const button = VRButton.createButton(renderer);
  document.body.appendChild(button);

  const state = { sessions: 0, connected: 0, selects: 0, grabs: 0, releases: 0, solves: 0, held: [null, null],
    carried: [null, null], menu: [] };
  const menu = new VRMenu();
  renderer.xr.addEventListener('sessionstart', () => { state.sessions += 1; });

  const raycaster = new THREE.Raycaster();
  const rayGeometry = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3(0, 0, -1)]);
  const controllers = [0, 1].map((index) => {
    const controller = renderer.xr.getController(index);
    const ray = new THREE.Line(rayGeometry, new THREE.LineBasicMaterial({ color: 0xffaa55 }));
    ray.scale.z = 3;
    controller.add(ray);
    const grip = new THREE.Mesh(new THREE.SphereGeometry(0.015, 12, 8),
      new THREE.MeshStandardMaterial({ color: 0xffaa55 }));
    controller.add(grip);
    scene.add(controller);

    controller.addEventListener('connected', () => { state.connected += 1; });
    controller.addEventListener('disconnected', () => { state.connected -= 1; });
    if (index === 0) controller.add(menu.mesh);
    controller.addEventListener('selectstart', () => {
      state.selects += 1;
      raycaster.setFromXRController(controller);
      const button = raycaster.intersectObject(menu.mesh, false).map((h) => menu.buttonAt(h.uv)).find(Boolean);
      if (button) {
        menu.press(button);
        state.menu.push(button);
        // half a metre in front of the eyes: where the user sees it, and can point at it to grab it
        const head = renderer.xr.getCamera();
        const eye = head.getWorldPosition(new THREE.Vector3());
        const at = world.worldToLocal(eye.addScaledVector(head.getWorldDirection(new THREE.Vector3()), AHEAD)).toArray();
        try {
          Promise.resolve(onMenu(button, at)).catch((err) => console.error(err));
        } catch (err) {
          console.error(err);
        }
        return;
      }
      const hits = raycaster.intersectObjects(grabbable(), true);
      const hit = hits.find((h) => h.object.visible);
      if (!hit) return;
      let group = hit.object;
      while (group.parent && group.parent !== world) group = group.parent;
      if (group.parent !== world) return;
      onGrab(group);
      if (!movable(group)) return; // selected, not carried
      controller.attach(group); // keeps its world pose; follows the controller from now on
      state.held[index] = group;
      state.grabs += 1;
    });
    controller.addEventListener('selectend', () => {
      const group = state.held[index];
      if (!group) return;
      world.attach(group);
      state.held[index] = null;
      state.carried[index] = null;
      state.releases += 1;
      onRelease(group);
    });
    controller.addEventListener('squeezestart', () => {
      state.solves += 1;
      try {
        onSolve();
      } catch (err) {
        console.error(err);
      }
    });
    return controller;
  });

  return {
    button,
    controllers,
    menu,
    update() { // onCarry for each carried group that moved since the last frame
      state.held.forEach((group, index) => {
        if (!group) return;
        const now = group.getWorldPosition(new THREE.Vector3()).toArray()
          .concat(group.getWorldQuaternion(new THREE.Quaternion()).toArray());
        const last = state.carried[index];
        state.carried[index] = now;
        if (last && now.every((v, i) => Math.abs(v - last[i]) < 1e-6)) return;
        onCarry(group);
      });
    },
    state: () => ({
      presenting: renderer.xr.isPresenting,
      sessions: state.sessions,
      connected: state.connected,
      selects: state.selects,
      controllers: controllers.map((c) => c.getWorldPosition(new THREE.Vector3()).toArray()),
      grabs: state.grabs,
      releases: state.releases,
      solves: state.solves,
      holding: state.held.map((g) => g?.userData.objectId ?? null),
      menuPresses: [...state.menu],
      menuStatus: menu.status,
      button: button.textContent,
    }),
  };
}
