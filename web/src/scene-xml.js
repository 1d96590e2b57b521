// Scene XML (shared/spec/scene-format.md) read into a small model that keeps its DOM, so an
// edited scene is written back with everything the viewer does not touch (comments, backend
// attributes of <simulation>, penalties, exploration) exactly as it was.

import { readBelief, writeBelief } from './scene-belief.js';

const XML_HEADER = '<?xml version="1.0" encoding="UTF-8"?>\n';

// The declaration, then the document's top-level nodes (comments, <scene>) one per line.
// (Browsers differ on whether XMLSerializer writes the declaration itself, so it never does here.)
function serialize(doc) {
  const serializer = new XMLSerializer();
  return XML_HEADER + [...doc.childNodes].map((n) => serializer.serializeToString(n)).join('\n') + '\n';
}

export function numbers(text, fallback) {
  if (text == null || text.trim() === '') return fallback;
  return text.trim().split(/\s+/).map(Number);
}

// Six decimals (micrometres, micro-radians), no exponent, no "-0".
export function fmt(x) {
  const s = Number(Number(x).toFixed(6)).toString();
  return s === '-0' ? '0' : s;
}

const vec = (values) => values.map(fmt).join(' ');

function child(el, tag) {
  for (const c of el.children) if (c.tagName === tag) return c;
  return null;
}

function ensureChild(el, tag, attrs = {}) {
  let c = child(el, tag);
  if (!c) {
    c = el.ownerDocument.createElementNS(null, tag);
    for (const [k, v] of Object.entries(attrs)) c.setAttribute(k, v);
    el.appendChild(c);
  }
  return c;
}

function normalizePath(path) {
  const out = [];
  for (const part of path.split('/')) {
    if (part === '' || part === '.') continue;
    if (part === '..' && out.length && out[out.length - 1] !== '..') out.pop();
    else out.push(part);
  }
  return out.join('/');
}

// Index of the last of several <target> elements: the one without `time`, else the latest time.
function lastOf(els) {
  let best = -1;
  let bestTime = -Infinity;
  for (const [i, el] of els.entries()) {
    if (!el.hasAttribute('time')) return i;
    const t = Number(el.getAttribute('time'));
    if (best < 0 || t > bestTime) {
      best = i;
      bestTime = t;
    }
  }
  return best;
}

// An <object> element as the viewer's record of it.
function objectOf(el) {
  const pose = child(el, 'pose');
  return {
    id: el.getAttribute('id'),
    el,
    shape: el.getAttribute('shape'),
    mesh: el.getAttribute('mesh'),
    spheres: el.getAttribute('spheres'),
    robot: el.getAttribute('urdf') || el.getAttribute('mjcf'), // its links come from the server
    size: numbers(el.getAttribute('size'), [1, 1, 1]),
    radius: Number(el.getAttribute('radius') ?? 0.5),
    height: Number(el.getAttribute('height') ?? 1),
    position: numbers(pose?.getAttribute('position'), [0, 0, 0]),
    orientation: numbers(pose?.getAttribute('orientation'), [1, 0, 0, 0]),
  };
}

export class SceneModel {
  // text: the XML; origin: the scene's path inside the server's scene root ('' for an upload).
  constructor(text, origin = '') {
    const doc = new DOMParser().parseFromString(text, 'application/xml');
    const bad = doc.getElementsByTagName('parsererror')[0];
    if (bad) throw new Error(`not well-formed XML: ${bad.textContent.trim().split('\n')[0]}`);
    if (doc.documentElement.tagName !== 'scene') {
      throw new Error(`the root element is <${doc.documentElement.tagName}>, not <scene>`);
    }
    this.doc = doc;
    this.root = doc.documentElement;
    this.origin = origin;
    this.name = this.root.getAttribute('name') || origin || 'scene';
    this.objects = [...this.root.children].filter((e) => e.tagName === 'object').map(objectOf);
  }

  // ---------------------------------------------------------------- objects
  // A new object after the last <object> (before <inference>): {shape: box|sphere|cylinder, size,
  // radius, height} or {mesh, spheres} (paths inside the scene root, written relative to the
  // scene's folder), at position [x, y, z], movable unless `fixed`. Returns its record; its id is
  // the shape's or mesh's name with the first free number ("box1", "mug2").
  addObject({ shape = null, size, radius, height, mesh = null, spheres = null, position, fixed = false }) {
    const stem = shape || (mesh.split('/').pop().replace(/\.[^.]*$/, '').replace(/[^A-Za-z0-9_-]/g, '_') || 'mesh');
    let n = 1;
    while (this.object(`${stem}${n}`)) n += 1;
    const el = this.doc.createElementNS(null, 'object');
    el.setAttribute('id', `${stem}${n}`);
    if (mesh) {
      el.setAttribute('mesh', this.relativePath(mesh));
      if (spheres) el.setAttribute('spheres', this.relativePath(spheres));
    } else if (shape === 'box') {
      el.setAttribute('shape', 'box');
      el.setAttribute('size', vec(size ?? [0.1, 0.1, 0.1]));
    } else if (shape === 'sphere' || shape === 'cylinder') {
      el.setAttribute('shape', shape);
      el.setAttribute('radius', fmt(radius ?? 0.05));
      if (shape === 'cylinder') el.setAttribute('height', fmt(height ?? 0.1));
    } else {
      throw new Error(`unknown shape ${shape}: box, sphere, cylinder or a mesh`);
    }
    if (fixed) el.setAttribute('fixed', 'true');
    const pose = this.doc.createElementNS(null, 'pose');
    pose.setAttribute('position', vec(position));
    pose.setAttribute('orientation', '1 0 0 0');
    el.appendChild(pose);
    const objects = [...this.root.children].filter((e) => e.tagName === 'object');
    if (objects.length) objects[objects.length - 1].after(el);
    else if (this.inference) this.inference.before(el);
    else this.root.appendChild(el);
    const record = objectOf(el);
    this.objects.push(record);
    return record;
  }

  // Remove an object that is not the source; its penalties go with it.
  removeObject(id) {
    if (id === this.source) throw new Error(`${id} is the source: choose another source first`);
    const obj = this.object(id);
    if (!obj) throw new Error(`no object ${id}`);
    obj.el.remove();
    this.objects = this.objects.filter((o) => o !== obj);
    for (const p of this.inference ? [...this.inference.children] : []) {
      if (p.tagName === 'penalty' && (p.getAttribute('between') || '').split(/\s+/).includes(id)) p.remove();
    }
  }

  // <simulation duration> (s; the spec's reader's default 1.5 where it is left out).
  get duration() {
    const sim = child(this.root, 'simulation');
    const d = Number(sim?.getAttribute('duration'));
    return Number.isFinite(d) && d > 0 ? d : 1.5;
  }

  // ---------------------------------------------------------------- what is believed (scene-belief.js)
  get belief() {
    return readBelief(this.inference);
  }

  setBelief(values) {
    if (!this.inference) throw new Error('choose a source first: the scene has no <inference>');
    writeBelief(this.inference, values);
  }

  object(id) {
    return this.objects.find((o) => o.id === id) || null;
  }

  isFixed(id) {
    return this.object(id)?.el.getAttribute('fixed') === 'true';
  }

  setFixed(id, fixed) {
    const obj = this.object(id);
    if (fixed) obj.el.setAttribute('fixed', 'true');
    else obj.el.removeAttribute('fixed');
  }

  // position: [x, y, z]; orientation: [w, x, y, z].
  setPose(id, position, orientation) {
    const obj = this.object(id);
    obj.position = [...position];
    obj.orientation = [...orientation];
    const pose = ensureChild(obj.el, 'pose');
    pose.setAttribute('position', vec(position));
    pose.setAttribute('orientation', vec(orientation));
  }

  get inference() {
    return child(this.root, 'inference');
  }

  get source() {
    return this.inference?.getAttribute('source') || null;
  }

  // Make `id` the source; a scene without <inference> gets one, its target where the object is. A
  // <start-area> that does not hold the new source's set-up position is moved, its size kept, to
  // centre on it (it bounded another object's start); returns true where it was moved.
  setSource(id) {
    const obj = this.object(id);
    let inf = this.inference;
    if (!inf) {
      inf = this.doc.createElementNS(null, 'inference');
      this.root.appendChild(inf);
    }
    inf.setAttribute('source', id);
    ensureChild(inf, 'target', { position: vec(obj.position), orientation: vec(obj.orientation) });
    this.setFixed(id, false);
    const area = this.startArea;
    if (!area || obj.position.every((v, i) => area.min[i] - 1e-9 <= v && v <= area.max[i] + 1e-9)) return false;
    const shift = obj.position.map((v, i) => v - (area.min[i] + area.max[i]) / 2);
    const el = child(inf, 'start-area');
    el.setAttribute('min', vec(area.min.map((v, i) => v + shift[i])));
    el.setAttribute('max', vec(area.max.map((v, i) => v + shift[i])));
    return true;
  }

  // ---------------------------------------------------------------- observations (<target>s)
  // Every <target> is one observation of the source ("how the source was seen"): a pose, or a
  // position alone (no orientation), at a `time` (a tracked source) or, without one, at the end;
  // `moving` true / false, else the default: seen lying still when it has no time and no velocities.

  targetElements() {
    return this.inference ? [...this.inference.children].filter((e) => e.tagName === 'target') : [];
  }

  // The observations in file order, as plain data (no DOM): index, position, orientation (null:
  // position only), time (null: not known), moving (null: the default), linearVelocity /
  // angularVelocity (null when not observed), atRest, last (the observation `target` is).
  get targets() {
    const els = this.targetElements();
    const lastIndex = lastOf(els);
    return els.map((el, index) => {
      const time = el.hasAttribute('time') ? Number(el.getAttribute('time')) : null;
      const movingAttr = el.getAttribute('moving');
      const moving = movingAttr == null ? null : movingAttr.trim() === 'true' || movingAttr.trim() === '1';
      const linearVelocity = numbers(el.getAttribute('linear-velocity'), null);
      const angularVelocity = numbers(el.getAttribute('angular-velocity'), null);
      const atRest = moving != null ? !moving : time == null && !linearVelocity && !angularVelocity;
      return {
        index,
        position: numbers(el.getAttribute('position'), [0, 0, 0]),
        orientation: numbers(el.getAttribute('orientation'), null),
        time,
        moving,
        linearVelocity,
        angularVelocity,
        atRest,
        last: index === lastIndex,
      };
    });
  }

  // Index of the last observation: the one without a time (seen at the end), else the latest time
  // (the first of those that share it); -1 without targets. (dejaview.scene.model.last_target)
  get lastTargetIndex() {
    return lastOf(this.targetElements());
  }

  // The last observation (what the "Target" ghost edits), or null.
  get target() {
    const all = this.targets;
    const i = this.lastTargetIndex;
    return i < 0 ? null : all[i];
  }

  // Move observation `index` (default: the last). A position-only observation stays one: its
  // orientation is written only where the target has one (setObservation changes what was seen).
  setTarget(position, orientation, index = this.lastTargetIndex) {
    let el = this.targetElements()[index];
    if (!el) {
      if (!this.inference) throw new Error('choose a source first: the scene has no <inference>');
      el = ensureChild(this.inference, 'target', { orientation: vec([1, 0, 0, 0]) });
    }
    el.setAttribute('position', vec(position));
    if (orientation && el.hasAttribute('orientation')) el.setAttribute('orientation', vec(orientation));
  }

  // Edit observation `index`: each of position, orientation, time, moving given is written; null
  // removes the attribute (orientation: position only; time: at the end; moving: the default).
  setObservation(index, { position, orientation, time, moving } = {}) {
    const el = this.targetElements()[index];
    if (!el) throw new Error(`no observation ${index}: the scene has ${this.targetElements().length}`);
    const put = (name, value, text) => {
      if (value === undefined) return;
      if (value === null) el.removeAttribute(name);
      else el.setAttribute(name, text(value));
    };
    put('position', position, vec);
    put('orientation', orientation, vec);
    put('time', time, fmt);
    put('moving', moving, (m) => (m ? 'true' : 'false'));
  }

  // A new observation after the last <target>; returns its index.
  addObservation({ position, orientation = null, time = null, moving = null }) {
    if (!this.inference) throw new Error('choose a source first: the scene has no <inference>');
    const els = this.targetElements();
    const el = this.doc.createElementNS(null, 'target');
    el.setAttribute('position', vec(position));
    if (els.length) els[els.length - 1].after(el);
    else this.inference.prepend(el);
    const index = els.length;
    this.setObservation(index, { orientation: orientation ?? undefined, time: time ?? undefined,
      moving: moving ?? undefined });
    return index;
  }

  removeObservation(index) {
    const els = this.targetElements();
    if (els.length <= 1) throw new Error('an inference needs at least one observation');
    if (!els[index]) throw new Error(`no observation ${index}: the scene has ${els.length}`);
    els[index].remove();
  }

  get startArea() {
    const a = this.inference && child(this.inference, 'start-area');
    if (!a) return null;
    return { min: numbers(a.getAttribute('min')), max: numbers(a.getAttribute('max')) };
  }

  // The inference settings the panel edits; '' means "the default" (attribute absent: 200
  // iterations, the default search).
  get settings() {
    const inf = this.inference;
    const heat = inf && child(inf, 'heatmap');
    return {
      iterations: inf?.hasAttribute('iterations') ? Number(inf.getAttribute('iterations')) : '',
      optimizer: inf?.getAttribute('optimizer') || 'auto',
      gradient: inf?.getAttribute('gradient') || '',
      heatmap: Boolean(heat),
      cells: numbers(heat?.getAttribute('cells'), [32, 32]),
    };
  }

  setSettings({ iterations, optimizer, gradient, heatmap, cells }) {
    const inf = this.inference;
    if (!inf) throw new Error('choose a source first: the scene has no <inference>');
    if (iterations === '' || iterations === null) inf.removeAttribute('iterations');
    else if (iterations !== undefined) inf.setAttribute('iterations', String(Math.max(1, Math.round(iterations))));
    if (optimizer !== undefined) {
      // 'auto' is the default: the attribute stays out, as the Python writer leaves it
      if (optimizer && optimizer !== 'auto') inf.setAttribute('optimizer', optimizer);
      else inf.removeAttribute('optimizer');
    }
    if (gradient !== undefined) {
      if (gradient) inf.setAttribute('gradient', gradient);
      else inf.removeAttribute('gradient');
    }
    if (heatmap === false) child(inf, 'heatmap')?.remove();
    if (heatmap || (cells && child(inf, 'heatmap'))) {
      const heat = ensureChild(inf, 'heatmap', { cells: '32 32' });
      if (cells) heat.setAttribute('cells', cells.map((c) => String(Math.max(1, Math.round(c)))).join(' '));
      if (!child(inf, 'start-area')) {
        // a heatmap needs a start area: +-0.25 m around the source's set-up position
        const p = this.object(this.source).position;
        ensureChild(inf, 'start-area', {
          min: vec([p[0] - 0.25, p[1] - 0.25, p[2]]),
          max: vec([p[0] + 0.25, p[1] + 0.25, p[2]]),
        });
      }
    }
  }

  // The scene as the user would save it: file names as written, relative to the scene's folder.
  toXml() {
    return serialize(this.doc);
  }

  // A file name of the scene as a path inside the scene root (how the server resolves scene_xml).
  rootPath(name) {
    if (name.startsWith('/') || /^[A-Za-z]:/.test(name)) return name;
    const dir = this.origin.includes('/') ? this.origin.slice(0, this.origin.lastIndexOf('/') + 1) : '';
    return normalizePath(dir + name);
  }

  // A path inside the scene root as the scene's files name it: relative to the scene's folder.
  relativePath(rootPath) {
    const dir = this.origin.includes('/') ? this.origin.slice(0, this.origin.lastIndexOf('/')).split('/') : [];
    const parts = normalizePath(rootPath).split('/');
    let common = 0;
    while (common < dir.length && common < parts.length - 1 && dir[common] === parts[common]) common += 1;
    return [...dir.slice(common).map(() => '..'), ...parts.slice(common)].join('/');
  }

  // The scene as a job's scene_xml: mesh and packing names rewritten relative to the scene root.
  // start: an initial state of the source ({position, orientation, linear_velocity,
  // angular_velocity}, result.json's initial_state) to simulate from instead of its set-up one.
  toServerXml(start = null) {
    const doc = this.doc.cloneNode(true);
    for (const el of doc.documentElement.children) {
      if (el.tagName !== 'object') continue;
      if (start && el.getAttribute('id') === this.source) {
        const pose = ensureChild(el, 'pose');
        pose.setAttribute('position', vec(start.position));
        pose.setAttribute('orientation', vec(start.orientation));
        const velocity = ensureChild(el, 'velocity');
        velocity.setAttribute('linear', vec(start.linear_velocity));
        velocity.setAttribute('angular', vec(start.angular_velocity));
      }
      for (const attr of ['mesh', 'spheres']) {
        const name = el.getAttribute(attr);
        if (name) el.setAttribute(attr, this.rootPath(name));
      }
    }
    return serialize(doc);
  }
}
