// The observations of the source (every <target>, "how the source was seen"): a translucent copy of
// the source at each observed pose, a small marker (sphere and cross) where only the position was
// seen, each labelled with its time ("0.35 s", "at rest" for the source seen lying still), and a
// dashed line through them in time order. The last observation keeps the source's colour (the
// "Target" ghost); the others are amber. Playback lights an observation up as it passes its time.
import * as THREE from 'three';

export const FINAL_COLOUR = 0xff7f0e; // the source's colour
export const OBSERVATION_COLOUR = 0xffc247;
const FINAL_OPACITY = 0.35;
const OBSERVATION_OPACITY = 0.22;
const LABEL_HEIGHT = 0.032; // of the view's height (sizeAttenuation off: the same size at any distance)

// The label of an observation: its time, "at rest" when it was seen lying still.
export function observationText(target) {
  const time = target.time != null ? `${Number(target.time).toFixed(2)} s` : null;
  if (target.atRest) return time ? `${time}, at rest` : 'at rest';
  return time ?? 'seen moving';
}

function noRaycast() {}

// A text sprite drawn over everything, its bottom centre at its position.
function labelSprite(text, colour) {
  const canvas = document.createElement('canvas');
  const material = new THREE.SpriteMaterial({ transparent: true, depthTest: false, depthWrite: false,
    sizeAttenuation: false });
  const sprite = new THREE.Sprite(material);
  sprite.center.set(0.5, 0);
  sprite.renderOrder = 10;
  sprite.raycast = noRaycast;
  sprite.userData.draw = (highlighted) => {
    const scale = 2; // pixels per CSS pixel of the texture, for sharp text
    const font = `600 ${13 * scale}px system-ui, sans-serif`;
    const ctx = canvas.getContext('2d');
    ctx.font = font;
    const w = Math.ceil(ctx.measureText(text).width) + 14 * scale;
    const h = 22 * scale;
    canvas.width = w;
    canvas.height = h;
    ctx.font = font;
    const hex = `#${colour.toString(16).padStart(6, '0')}`;
    ctx.fillStyle = highlighted ? hex : 'rgba(27, 31, 39, 0.82)';
    ctx.strokeStyle = hex;
    ctx.lineWidth = 2 * scale;
    ctx.beginPath();
    ctx.roundRect(scale, scale, w - 2 * scale, h - 2 * scale, 5 * scale);
    ctx.fill();
    ctx.stroke();
    ctx.fillStyle = highlighted ? '#1b1f27' : '#f2f2f2';
    ctx.textBaseline = 'middle';
    ctx.fillText(text, 7 * scale, h / 2 + scale);
    material.map?.dispose();
    material.map = new THREE.CanvasTexture(canvas);
    material.map.colorSpace = THREE.SRGBColorSpace;
    material.needsUpdate = true;
    sprite.scale.set((LABEL_HEIGHT * w) / h, LABEL_HEIGHT, 1);
  };
  sprite.userData.draw(false);
  return sprite;
}

// One observation's 3D objects. target: SceneModel.targets' row; sourceVisual: the source's
// Object3D (its copy is the ghost); radius: the source's bounding radius (m); id: selection id.
export function buildObservation(target, sourceVisual, radius, id) {
  const colour = target.last ? FINAL_COLOUR : OBSERVATION_COLOUR;
  const opacity = target.last ? FINAL_OPACITY : OBSERVATION_OPACITY;
  const group = new THREE.Group();
  const materials = [];
  const kind = target.orientation && sourceVisual ? 'pose' : 'position';
  let lift = Math.max(0.03, radius); // the label: above the source's top, whatever way it is turned
  if (kind === 'pose') {
    const copy = sourceVisual.clone(true);
    copy.visible = true;
    const edges = [];
    copy.traverse((m) => {
      if (!m.isMesh) return;
      const material = new THREE.MeshStandardMaterial({ color: colour, emissive: colour, emissiveIntensity: 0,
        transparent: true, opacity, depthWrite: false });
      materials.push(material);
      m.material = material;
      // the earlier observations get their edges too: a faint copy reads better with an outline
      const triangles = (m.geometry.index?.count ?? m.geometry.attributes.position.count) / 3;
      if (!target.last && !m.isInstancedMesh && triangles <= 20000) edges.push(m);
    });
    for (const m of edges) {
      const lines = new THREE.LineSegments(new THREE.EdgesGeometry(m.geometry, 30),
        new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.7, depthWrite: false }));
      lines.raycast = noRaycast;
      m.add(lines);
    }
    group.add(copy);
  } else {
    // position only (or the source is not drawn): a sphere with a cross through it
    const r = Math.min(0.06, Math.max(0.01, radius * 0.22));
    lift = 2.6 * r;
    const material = new THREE.MeshStandardMaterial({ color: colour, emissive: colour, emissiveIntensity: 0.15,
      transparent: true, opacity: 0.9, depthWrite: false });
    materials.push(material);
    group.add(new THREE.Mesh(new THREE.SphereGeometry(r, 20, 12), material));
    const a = 2.2 * r;
    const cross = new THREE.LineSegments(
      new THREE.BufferGeometry().setFromPoints([[-a, 0, 0], [a, 0, 0], [0, -a, 0], [0, a, 0], [0, 0, -a], [0, 0, a]]
        .map((p) => new THREE.Vector3(...p))),
      new THREE.LineBasicMaterial({ color: colour }));
    cross.raycast = noRaycast;
    group.add(cross);
  }
  group.traverse((m) => { m.userData.objectId = id; });
  group.userData.objectId = id;
  group.userData.observation = target.index;
  group.name = `observation-${target.index}`;
  const text = observationText(target);
  const label = labelSprite(text, colour);
  label.name = `observation-label-${target.index}`;
  return {
    index: target.index, id, last: target.last, kind, text, group, label, materials,
    opacity: kind === 'pose' ? opacity : 0.9, colour, highlighted: false, labelLift: lift,
  };
}

// Light an observation up (playback passes its time) or back to its normal look.
export function highlightObservation(obs, on) {
  if (obs.highlighted === on) return;
  obs.highlighted = on;
  for (const m of obs.materials) {
    m.opacity = on ? Math.max(0.6, obs.opacity) : obs.opacity;
    m.emissiveIntensity = on ? 0.55 : (obs.kind === 'pose' ? 0 : 0.15);
  }
  obs.group.scale.setScalar(on && obs.kind === 'position' ? 1.5 : 1);
  obs.label.userData.draw(on);
}

// A dashed line through the observed positions in time order (the end last).
export function observationLine(observations, targets) {
  const order = targets.map((t, i) => i)
    .sort((a, b) => (targets[a].time ?? Infinity) - (targets[b].time ?? Infinity) || a - b);
  const points = order.map((i) => observations[i].group.position.clone());
  const geometry = new THREE.BufferGeometry().setFromPoints(points);
  const length = points.slice(1).reduce((s, p, i) => s + p.distanceTo(points[i]), 0);
  const dash = Math.max(0.005, length / 120);
  const line = new THREE.Line(geometry, new THREE.LineDashedMaterial({
    color: OBSERVATION_COLOUR, dashSize: dash, gapSize: dash, transparent: true, opacity: 0.6, depthWrite: false,
  }));
  line.computeLineDistances();
  line.raycast = noRaycast;
  line.name = 'observation-line';
  line.userData.order = order;
  return line;
}

// Move the line's points to where the observations are now (after an edit).
export function updateObservationLine(line, observations) {
  const attr = line.geometry.attributes.position;
  line.userData.order.forEach((i, k) => attr.setXYZ(k, ...observations[i].group.position.toArray()));
  attr.needsUpdate = true;
  line.computeLineDistances();
  line.geometry.computeBoundingSphere();
}
