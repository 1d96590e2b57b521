// The VR menu: a small board above the left controller whose buttons the other controller's ray
// presses (trigger): add a timed target where the controller is, delete one, shift its time, add a
// box / sphere / cylinder / mesh there, make the held-last object the source or fixed, remove it,
// solve. Its top line says what is selected. The panel's controls, for a user who cannot see the page.
import * as THREE from 'three';

export const MENU_BUTTONS = [
  ['+ target', 'add-target'], ['− target', 'delete-target'], ['time −', 'time-down'], ['time +', 'time-up'],
  ['box', 'box'], ['sphere', 'sphere'], ['cylinder', 'cylinder'], ['mesh', 'mesh'],
  ['source', 'source'], ['fixed', 'fixed'], ['remove', 'remove'], ['solve', 'solve'],
];
const COLUMNS = 4;
const ROWS = MENU_BUTTONS.length / COLUMNS;
const WIDTH = 0.28; // m
const HEIGHT = 0.16;
const STATUS = 0.22; // of the height: the status line
const PX = 1024; // texture width

export class VRMenu {
  constructor() {
    this.canvas = document.createElement('canvas');
    this.canvas.width = PX;
    this.canvas.height = Math.round((PX * HEIGHT) / WIDTH);
    this.texture = new THREE.CanvasTexture(this.canvas);
    this.texture.colorSpace = THREE.SRGBColorSpace;
    this.mesh = new THREE.Mesh(new THREE.PlaneGeometry(WIDTH, HEIGHT),
      new THREE.MeshBasicMaterial({ map: this.texture, transparent: true, side: THREE.DoubleSide }));
    this.mesh.name = 'vr-menu';
    // above the left controller, facing the user (tilted back towards the eyes)
    this.mesh.position.set(0, 0.11, -0.06);
    this.mesh.rotation.x = -0.3;
    this.status = '';
    this.pressed = null;
    this.draw();
  }

  setStatus(text) {
    if (text === this.status) return;
    this.status = text;
    this.draw();
  }

  draw() {
    const ctx = this.canvas.getContext('2d');
    const { width: w, height: h } = this.canvas;
    ctx.clearRect(0, 0, w, h);
    ctx.fillStyle = 'rgba(27, 31, 39, 0.92)';
    ctx.beginPath();
    ctx.roundRect(0, 0, w, h, 24);
    ctx.fill();
    ctx.fillStyle = '#f2f2f2';
    ctx.font = '600 44px system-ui, sans-serif';
    ctx.textBaseline = 'middle';
    ctx.fillText(this.status || 'trigger: grab · squeeze: solve', 22, (h * STATUS) / 2, w - 44);
    const bw = w / COLUMNS;
    const bh = (h * (1 - STATUS)) / ROWS;
    ctx.font = '600 38px system-ui, sans-serif';
    ctx.textAlign = 'center';
    MENU_BUTTONS.forEach(([label, name], k) => {
      const x = (k % COLUMNS) * bw;
      const y = h * STATUS + Math.floor(k / COLUMNS) * bh;
      ctx.fillStyle = name === this.pressed ? '#c46a1c' : '#343b4a';
      ctx.strokeStyle = '#4a5366';
      ctx.lineWidth = 3;
      ctx.beginPath();
      ctx.roundRect(x + 8, y + 8, bw - 16, bh - 16, 14);
      ctx.fill();
      ctx.stroke();
      ctx.fillStyle = '#f2f2f2';
      ctx.fillText(label, x + bw / 2, y + bh / 2 + 2);
    });
    ctx.textAlign = 'left';
    this.texture.needsUpdate = true;
  }

  // The button under a ray hit's uv (the plane's uv: u right, v up), or null.
  buttonAt(uv) {
    const row = Math.floor(((1 - uv.y) - STATUS) / ((1 - STATUS) / ROWS));
    const col = Math.floor(uv.x * COLUMNS);
    if (row < 0 || row >= ROWS || col < 0 || col >= COLUMNS) return null;
    return MENU_BUTTONS[row * COLUMNS + col][1];
  }

  press(name) {
    this.pressed = name;
    this.draw();
    setTimeout(() => { if (this.pressed === name) { this.pressed = null; this.draw(); } }, 300);
  }

  // Where to hold a controller to press button `name`: 15 cm in front of it, pointing at it
  // (XR frame: {position: [x, y, z], quaternion: [x, y, z, w]}); for tests and a demo.
  aim(name) {
    const k = MENU_BUTTONS.findIndex(([, n]) => n === name);
    if (k < 0) throw new Error(`no menu button ${name}`);
    const u = ((k % COLUMNS) + 0.5) / COLUMNS;
    const v = 1 - (STATUS + ((Math.floor(k / COLUMNS) + 0.5) * (1 - STATUS)) / ROWS);
    this.mesh.updateMatrixWorld(true);
    const centre = this.mesh.localToWorld(new THREE.Vector3((u - 0.5) * WIDTH, (v - 0.5) * HEIGHT, 0));
    const normal = new THREE.Vector3(0, 0, 1).transformDirection(this.mesh.matrixWorld);
    const position = centre.clone().addScaledVector(normal, 0.15);
    const quaternion = new THREE.Quaternion().setFromUnitVectors(new THREE.Vector3(0, 0, -1), normal.clone().negate());
    return { position: position.toArray(), quaternion: quaternion.toArray() };
  }
}
