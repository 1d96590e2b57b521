// The three.js stage: renderer, camera, orbit controls, lights, the transform gizmo, and `world`, the
// group that holds everything of the scene in the scene's z-up frame.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { TransformControls } from 'three/addons/controls/TransformControls.js';

import { $ } from './state.js';

const viewport = $('viewport');
export const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(Math.min(2, window.devicePixelRatio));
viewport.appendChild(renderer.domElement);

export const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1b1f27);
export const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 200);
camera.position.set(1.8, 1.4, 2.2);
export const orbit = new OrbitControls(camera, renderer.domElement);
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
export const world = new THREE.Group();
world.rotation.x = -Math.PI / 2;
scene.add(world);

export const gizmo = new TransformControls(camera, renderer.domElement);
gizmo.setSize(0.8);
scene.add(gizmo.getHelper());
gizmo.addEventListener('dragging-changed', (e) => { orbit.enabled = !e.value; });

function resize() {
  const w = viewport.clientWidth || 1;
  const h = viewport.clientHeight || 1;
  renderer.setSize(w, h);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
}
window.addEventListener('resize', resize);
resize();
