// What is believed before looking (shared/spec/scene-format.md, "Additions to version 1"): the
// <inference> children the panel edits beside the observations: <prior speed spin tilt>,
// <observation sigma angle-sigma rest-speed rest-spin>, <posterior samples>, <physics-prior
// friction restitution stiffness> and <model-uncertainty friction restitution>. An attribute left
// out is the spec's default (a flat prior, the implementation's noise, no samples, known physics);
// an element left with no attribute is removed, so a scene the panel did not touch is written as read.

// element -> [[the panel's key, the XML attribute, its check], ...]
const POSITIVE = 'positive';
const NONNEGATIVE = 'nonnegative';
export const BELIEF_ELEMENTS = {
  prior: ['prior', [['speed', 'speed', POSITIVE], ['spin', 'spin', POSITIVE], ['tilt', 'tilt', POSITIVE]]],
  observation: ['observation', [['sigma', 'sigma', POSITIVE], ['angleSigma', 'angle-sigma', POSITIVE],
    ['restSpeed', 'rest-speed', POSITIVE], ['restSpin', 'rest-spin', POSITIVE]]],
  physicsPrior: ['physics-prior', [['friction', 'friction', NONNEGATIVE],
    ['restitution', 'restitution', NONNEGATIVE], ['stiffness', 'stiffness', NONNEGATIVE]]],
  modelUncertainty: ['model-uncertainty', [['friction', 'friction', NONNEGATIVE],
    ['restitution', 'restitution', NONNEGATIVE]]],
};

function child(el, tag) {
  for (const c of el.children) if (c.tagName === tag) return c;
  return null;
}

// Six decimals, no exponent, no "-0" (as scene-xml.js writes numbers).
function fmt(x) {
  const s = Number(Number(x).toFixed(6)).toString();
  return s === '-0' ? '0' : s;
}

// The belief as plain data: {prior: {speed, spin, tilt}, observation: {...}, physicsPrior: {...},
// modelUncertainty: {...}, samples}; null where an attribute is left out (samples: 0).
export function readBelief(inf) {
  const out = {};
  for (const [key, [tag, attrs]] of Object.entries(BELIEF_ELEMENTS)) {
    const el = inf && child(inf, tag);
    out[key] = Object.fromEntries(attrs.map(([name, attr]) => {
      const text = el?.getAttribute(attr);
      return [name, text == null || text.trim() === '' ? null : Number(text)];
    }));
  }
  const post = inf && child(inf, 'posterior');
  out.samples = post?.hasAttribute('samples') ? Number(post.getAttribute('samples')) : 0;
  return out;
}

function checked(what, value, check) {
  const x = Number(value);
  if (!Number.isFinite(x) || (check === POSITIVE ? x <= 0 : x < 0)) {
    throw new Error(`${what} must be a ${check === POSITIVE ? 'positive' : 'non-negative'} number, got ${value}`);
  }
  return x;
}

// Write the parts of `values` given (readBelief's shape): a number writes its attribute, null or ''
// removes it; `samples` 0 (or null) removes <posterior>. Throws on a value the spec's reader refuses,
// before anything is written.
export function writeBelief(inf, values) {
  const doc = inf.ownerDocument;
  const edits = [];
  for (const [key, [tag, attrs]] of Object.entries(BELIEF_ELEMENTS)) {
    const given = values[key];
    if (!given) continue;
    for (const [name, attr, check] of attrs) {
      if (!(name in given)) continue;
      const v = given[name];
      const empty = v === null || v === '' || v === undefined;
      edits.push([tag, attr, empty ? null : fmt(checked(`<${tag} ${attr}>`, v, check))]);
    }
  }
  let samples;
  if (values.samples !== undefined) {
    const n = values.samples === null || values.samples === '' ? 0 : Number(values.samples);
    if (!Number.isInteger(n) || n < 0) throw new Error(`<posterior samples> must be a whole number >= 0, got ${values.samples}`);
    samples = n;
  }
  for (const [tag, attr, text] of edits) {
    let el = child(inf, tag);
    if (text === null) {
      el?.removeAttribute(attr);
      if (el && el.attributes.length === 0) el.remove();
      continue;
    }
    if (!el) {
      el = doc.createElementNS(null, tag);
      inf.appendChild(el);
    }
    el.setAttribute(attr, text);
  }
  if (samples !== undefined) {
    let el = child(inf, 'posterior');
    if (samples === 0) el?.remove();
    else {
      if (!el) {
        el = doc.createElementNS(null, 'posterior');
        inf.appendChild(el);
      }
      el.setAttribute('samples', String(samples));
    }
  }
}
