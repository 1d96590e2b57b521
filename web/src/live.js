// Live answers (protocol.md, "Live answers"): while "live" is ticked, moving the target asks the
// server where the source came from for where it is seen now (a `live` message, answered from the
// scene's amortised model in milliseconds), and the heatmap and a cloud of start points follow.
// One message in flight: a move while one is answered is sent when that answer comes (the newest
// pose only), so the server never holds a backlog for this page. The scene text is kept while only
// the target moves (the server caches each scene text's posterior); any other edit sends it anew.
// "Train" submits a train job for the scene where the server has no model for it (`no_model`).
import * as THREE from 'three';

import { showHeatmap } from './result-view.js';
import { TARGET, fromQuat, groupOf } from './selection.js';
import { world } from './stage.js';
import { $, app, notify } from './state.js';

const PREFIX = 'live-';
const KEPT_LATENCIES = 50;

export class Live {
  constructor(connection) {
    this.connection = connection;
    this.enabled = false;
    this.xml = null; // the scene text live messages carry, until something but the target changes
    this.inFlight = null; // {id, movedAt}
    this.movedAt = null; // when the first move not yet asked about happened
    this.seq = 0;
    this.answers = 0;
    this.latencies = []; // ms from a move to its answer drawn
    this.fitted = null;
    this.error = null;
    this.cloud = null;
  }

  setEnabled(on) {
    this.enabled = on;
    this.error = null;
    if (on) this.moved(null);
    else this.clear();
    this.status();
  }

  // Something other than the target changed (an object, the source, settings, a new scene).
  sceneChanged() {
    this.xml = null;
  }

  clear() {
    this.cloud?.removeFromParent();
    this.cloud = null;
  }

  // A group was moved by the gizmo or a controller: the target asks again, anything else is a new scene.
  moved(group) {
    if (group && !(group === groupOf(TARGET))) this.sceneChanged();
    if (!this.enabled || !app.model) return;
    this.movedAt ??= performance.now();
    if (!this.inFlight) this.send();
  }

  send() {
    const ghost = groupOf(TARGET);
    if (!ghost) return;
    this.xml ??= app.model.toServerXml();
    const id = `${PREFIX}${++this.seq}`;
    this.inFlight = { id, movedAt: this.movedAt };
    this.movedAt = null;
    this.connection.send({
      type: 'live', scene_xml: this.xml, request_id: id,
      target: scenePose(ghost),
    });
  }

  // A message from the server: true where it was a live one (handled here).
  handle(msg) {
    if (typeof msg.request_id !== 'string' || !msg.request_id.startsWith(PREFIX)) return false;
    if (msg.type !== 'live-result' && msg.type !== 'error') return true;
    const asked = this.inFlight;
    this.inFlight = null;
    if (msg.type === 'error') {
      if (this.error?.code !== msg.code) notify(`live: ${msg.code}: ${msg.message}`, 'error');
      this.error = { code: msg.code, message: msg.message };
    } else if (this.enabled) {
      this.error = null;
      this.draw(msg);
      this.drawn = { movedAt: asked?.movedAt }; // counted when the next frame is rendered (frame())
    }
    if (this.enabled && this.movedAt != null) this.send();
    this.status();
    return true;
  }

  // Called by the render loop after each frame (the renderer's, which runs in VR too, where the
  // window's requestAnimationFrame does not): an answer drawn in it is counted, with its latency.
  frame() {
    if (!this.drawn) return;
    const { movedAt } = this.drawn;
    this.drawn = null;
    if (movedAt != null) this.latencies.push(performance.now() - movedAt);
    if (this.latencies.length > KEPT_LATENCIES) this.latencies.shift();
    this.answers += 1;
    this.status();
  }

  draw(msg) {
    this.fitted = msg.fitted;
    if (msg.heatmap) showHeatmap(msg.heatmap);
    this.clear();
    const positions = new Float32Array(msg.samples.flat());
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
    this.cloud = new THREE.Points(geometry, new THREE.PointsMaterial({
      size: 0.015, color: msg.fitted ? 0x4fc3f7 : 0x9e9e9e, transparent: true, opacity: 0.8, depthWrite: false,
    }));
    this.cloud.name = 'live-samples';
    this.cloud.visible = $('show-samples').checked;
    world.add(this.cloud);
  }

  status() {
    const last = this.latencies[this.latencies.length - 1];
    let text = '';
    if (this.error) text = this.error.code === 'no_model' ? 'no model for this scene: Train' : this.error.code;
    else if (this.enabled && last != null) {
      text = `${Math.round(last)} ms${this.fitted === false ? ', not like its training' : ''}`;
    }
    $('live-status').textContent = text;
  }

  // What the tests read (test-hooks.js).
  state() {
    return {
      enabled: this.enabled, answers: this.answers, latencies: [...this.latencies], fitted: this.fitted,
      error: this.error, samples: this.cloud ? this.cloud.geometry.attributes.position.count : 0,
      inFlight: Boolean(this.inFlight), probability: app.heatmapGrid?.probability ?? null,
    };
  }
}

// The pose of a group in the scene (the world group's frame), also while a controller carries it
// (attached to the controller, its own position is the controller's frame): { position, orientation }.
function scenePose(group) {
  if (group.parent === world) return { position: group.position.toArray(), orientation: fromQuat(group.quaternion) };
  const position = world.worldToLocal(group.getWorldPosition(new THREE.Vector3()));
  const q = world.getWorldQuaternion(new THREE.Quaternion()).invert()
    .multiply(group.getWorldQuaternion(new THREE.Quaternion()));
  return { position: position.toArray(), orientation: fromQuat(q) };
}
