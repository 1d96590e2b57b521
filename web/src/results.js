// Job results in the scene: the trajectory (a spline through the source's positions, poses over
// time for playback), the heatmap (a coloured decal on the surface under the start area), the
// posterior's samples, and result.json in words for the panel (summarizeResult).
import * as THREE from 'three';
import { DecalGeometry } from 'three/addons/geometries/DecalGeometry.js';

const HEADER = 'step,time,object,x,y,z,qw,qx,qy,qz';

// trajectory.csv -> {duration, objects: {id: {time: [], position: [[x,y,z]], orientation: [[w,x,y,z]]}}}
export function parseTrajectory(csv) {
  const lines = csv.trim().split(/\r?\n/);
  if (lines[0].trim() !== HEADER) throw new Error(`trajectory.csv: header is not ${HEADER}`);
  const objects = {};
  let duration = 0;
  for (const line of lines.slice(1)) {
    const f = line.split(',');
    if (f.length < 10) continue;
    const t = Number(f[1]);
    const track = (objects[f[2]] ??= { time: [], position: [], orientation: [] });
    track.time.push(t);
    track.position.push([Number(f[3]), Number(f[4]), Number(f[5])]);
    track.orientation.push([Number(f[6]), Number(f[7]), Number(f[8]), Number(f[9])]);
    duration = Math.max(duration, t);
  }
  return { duration, objects };
}

const qa = new THREE.Quaternion();
const qb = new THREE.Quaternion();

// The pose of one track at time t (linear in position, slerp in orientation), into obj3d.
export function applyPose(track, t, obj3d) {
  const times = track.time;
  let hi = times.findIndex((x) => x >= t);
  if (hi < 0) hi = times.length - 1;
  const lo = Math.max(0, hi - 1);
  const span = times[hi] - times[lo];
  const u = span > 0 ? Math.min(1, Math.max(0, (t - times[lo]) / span)) : 1;
  const a = track.position[lo];
  const b = track.position[hi];
  obj3d.position.set(a[0] + (b[0] - a[0]) * u, a[1] + (b[1] - a[1]) * u, a[2] + (b[2] - a[2]) * u);
  const [aw, ax, ay, az] = track.orientation[lo];
  const [bw, bx, by, bz] = track.orientation[hi];
  qa.set(ax, ay, az, aw).normalize();
  qb.set(bx, by, bz, bw).normalize();
  obj3d.quaternion.slerpQuaternions(qa, qb, u);
}

export function trajectorySpline(track, color = 0xff7f0e) {
  const stride = Math.max(1, Math.floor(track.position.length / 300));
  const points = track.position.filter((_, i) => i % stride === 0 || i === track.position.length - 1)
    .map((p) => new THREE.Vector3(...p));
  const group = new THREE.Group();
  group.name = 'trajectory';
  if (points.length < 2) return group;
  const curve = new THREE.CatmullRomCurve3(points, false, 'centripetal');
  const tube = new THREE.Mesh(new THREE.TubeGeometry(curve, Math.min(600, points.length * 4), 0.006, 8),
    new THREE.MeshStandardMaterial({ color, emissive: color, emissiveIntensity: 0.3 }));
  group.add(tube);
  const dot = new THREE.SphereGeometry(0.018, 16, 8);
  const start = new THREE.Mesh(dot, new THREE.MeshStandardMaterial({ color: 0x2ca02c }));
  start.position.copy(points[0]);
  const end = new THREE.Mesh(dot, new THREE.MeshStandardMaterial({ color: 0xd62728 }));
  end.position.copy(points[points.length - 1]);
  group.add(start, end);
  return group;
}

// viridis at a few stops, linearly interpolated
const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];

function colour(u) {
  const x = Math.min(1, Math.max(0, u)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const f = x - i;
  return VIRIDIS[i].map((c, k) => Math.round(c + (VIRIDIS[i + 1][k] - c) * f));
}

// heatmap.json -> an RGBA texture, row j from -y up (texture v grows with y), alpha by probability.
export function heatmapTexture(grid) {
  const [nx, ny] = grid.cells;
  const p = grid.probability;
  const peak = Math.max(1e-12, ...p.flat());
  const data = new Uint8Array(nx * ny * 4);
  for (let j = 0; j < ny; j++) {
    for (let i = 0; i < nx; i++) {
      const u = p[j][i] / peak;
      const [r, g, b] = colour(u);
      data.set([r, g, b, Math.round(90 + 165 * u)], (j * nx + i) * 4);
    }
  }
  const texture = new THREE.DataTexture(data, nx, ny, THREE.RGBAFormat);
  texture.magFilter = THREE.NearestFilter;
  texture.colorSpace = THREE.SRGBColorSpace;
  texture.needsUpdate = true;
  return texture;
}

// The heatmap on the surface under the start area: a decal projected straight down onto the first
// surface below the area's centre, or a flat square at that height when there is none to project on.
// world: the z-up group holding the scene; surfaces: meshes it may land on; topZ: the start area's top.
export function heatmapDecal(grid, world, surfaces, topZ) {
  const [x0, y0] = grid.min;
  const [x1, y1] = grid.max;
  const sx = Math.max(1e-3, x1 - x0);
  const sy = Math.max(1e-3, y1 - y0);
  const centre = new THREE.Vector3((x0 + x1) / 2, (y0 + y1) / 2, topZ + 0.01);
  const material = new THREE.MeshBasicMaterial({
    map: heatmapTexture(grid), transparent: true, depthWrite: false,
    polygonOffset: true, polygonOffsetFactor: -4, side: THREE.DoubleSide,
  });
  world.updateMatrixWorld(true);
  const ray = new THREE.Raycaster(world.localToWorld(centre.clone()),
    new THREE.Vector3(0, 0, -1).transformDirection(world.matrixWorld));
  const hit = ray.intersectObjects(surfaces, true)[0];
  let mesh;
  if (hit && hit.object.isMesh && !hit.object.isInstancedMesh) {
    // project along the scene's -z: the projector's z axis is the scene's z (the world group's y)
    const q = world.getWorldQuaternion(new THREE.Quaternion());
    const orientation = new THREE.Euler().setFromQuaternion(q);
    const depth = Math.max(sx, sy) + 0.5;
    const geometry = new DecalGeometry(hit.object, hit.point, orientation, new THREE.Vector3(sx, sy, depth));
    if (geometry.attributes.position.count > 0) {
      mesh = new THREE.Mesh(geometry, material);
      world.attach(mesh); // the decal's vertices are in world coordinates
    }
  }
  if (!mesh) {
    mesh = new THREE.Mesh(new THREE.PlaneGeometry(sx, sy), material);
    const z = hit ? world.worldToLocal(hit.point.clone()).z + 0.002 : 0.002;
    mesh.position.set(centre.x, centre.y, z);
    world.add(mesh);
  }
  mesh.name = 'heatmap';
  mesh.renderOrder = 2;
  return mesh;
}

const POSTERIOR_HEADER = 'sample,weight,x,y,z,qw,qx,qy,qz,vx,vy,vz,wx,wy,wz';

// posterior.csv -> [{weight, position: [x, y, z]}] (the source's start, object-frame origin)
export function parsePosterior(csv) {
  const lines = csv.trim().split(/\r?\n/);
  if (lines[0].trim() !== POSTERIOR_HEADER) throw new Error(`posterior.csv: header is not ${POSTERIOR_HEADER}`);
  return lines.slice(1).map((line) => line.split(',').map(Number)).filter((f) => f.length >= 5)
    .map((f) => ({ weight: f[1], position: [f[2], f[3], f[4]] }));
}

const PATHS_HEADER = 'sample,step,time,x,y,z';

// posterior_paths.csv -> [[x, y, z], ...] per sample (a few samples' pasts, the source's origin)
export function parsePosteriorPaths(csv) {
  const lines = csv.trim().split(/\r?\n/);
  if (lines[0].trim() !== PATHS_HEADER) throw new Error(`posterior_paths.csv: header is not ${PATHS_HEADER}`);
  const paths = new Map();
  for (const line of lines.slice(1)) {
    const f = line.split(',').map(Number);
    if (f.length < 6 || f.some((v) => !Number.isFinite(v))) continue;
    if (!paths.has(f[0])) paths.set(f[0], []);
    paths.get(f[0]).push([f[3], f[4], f[5]]);
  }
  return [...paths.values()].filter((points) => points.length >= 2);
}

// A few posterior samples' trajectories as faint lines (other pasts that explain the same end).
export function samplePaths(paths) {
  const group = new THREE.Group();
  const material = new THREE.LineBasicMaterial({
    color: 0x9ecbff, transparent: true, opacity: 0.35, depthWrite: false,
  });
  for (const points of paths) {
    const geometry = new THREE.BufferGeometry().setFromPoints(points.map((p) => new THREE.Vector3(...p)));
    group.add(new THREE.Line(geometry, material));
  }
  group.name = 'posterior-paths';
  group.renderOrder = 3;
  return group;
}

// The posterior samples' start points, each coloured by the posterior probability around it: its
// weight times the number of samples within `radius` (a kernel density estimate), on the heatmap's
// colour scale (dark: few pasts start here, yellow: many).
export function sampleCloud(samples, radius = 0.02) {
  const n = samples.length;
  const density = new Float32Array(n);
  for (let i = 0; i < n; i += 1) {
    const [xi, yi, zi] = samples[i].position;
    let d = 0;
    for (let j = 0; j < n; j += 1) {
      const [xj, yj, zj] = samples[j].position;
      const r2 = (xi - xj) ** 2 + (yi - yj) ** 2 + (zi - zj) ** 2;
      if (r2 < radius * radius) d += samples[j].weight;
    }
    density[i] = d;
  }
  const top = Math.max(...density, 1e-12);
  const positions = new Float32Array(3 * n);
  const colours = new Float32Array(3 * n);
  samples.forEach((s, i) => {
    positions.set(s.position, 3 * i);
    const [r, g, b] = colour(density[i] / top);
    colours.set([r / 255, g / 255, b / 255], 3 * i);
  });
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  const points = new THREE.Points(geometry, new THREE.PointsMaterial({
    size: 0.025, vertexColors: true, transparent: true, opacity: 0.9, depthWrite: false,
  }));
  points.name = 'posterior-samples';
  points.renderOrder = 3;
  return points;
}

// ------------------------------------------------------------------ result.json, in words

// A distance in metres as a reader checks it: "0.2 mm", "36 mm", "1.25 m".
export function formatDistance(m) {
  const mm = Number(m) * 1000;
  if (!Number.isFinite(mm)) return '?';
  if (mm < 10) return `${mm.toFixed(1)} mm`;
  if (mm < 1000) return `${Math.round(mm)} mm`;
  return `${(mm / 1000).toFixed(2)} m`;
}

export function formatAngle(deg) {
  const d = Number(deg);
  if (!Number.isFinite(d)) return '?';
  return d < 10 ? `${d.toFixed(1)}°` : `${Math.round(d)}°`;
}

const off = (row) => formatDistance(row.position_error)
  + (row.angle_error_deg == null ? '' : ` / ${formatAngle(row.angle_error_deg)}`);

// The last of several targets (as result.json lists them): the one without a time, else the latest.
function lastIndex(targets) {
  let best = -1;
  for (const [i, t] of targets.entries()) {
    if (t.time == null) return i;
    if (best < 0 || t.time > targets[best].time) best = i;
  }
  return best;
}

// When the answer meets each observation (s), for lighting them up during playback: result.json's
// `observations` (the moment compared; a target seen moving at a moment not known: its best match)
// where the result has one row per target, else each target's time, the end (`duration`) without.
export function observationTimes(targets, result, duration) {
  const rows = result?.observations;
  const fromResult = Array.isArray(rows) && rows.length === targets.length;
  return targets.map((t, i) => {
    const row = fromResult ? rows[i] : null;
    const at = row ? (row.matched?.time ?? row.time) : (t.time ?? duration);
    return Number.isFinite(at) ? at : null;
  });
}

// result.json in lines for the panel, [{kind, text}]: the best loss; how far the END is from where
// the source was last seen (`end_error`: "ends 0.2 mm / 0.6° from where it was seen lying"); when it
// came to rest (`rest`); for a tracked source, the answer against each observation at its moment
// (`observations`); the warnings (`warnings`; the sampler's agreement: posterior-view.js).
export function summarizeResult(result) {
  const lines = [];
  if (!result) return lines;
  if (Number.isFinite(result.loss)) lines.push({ kind: 'info', text: `best loss ${result.loss.toPrecision(3)}` });
  const targets = Array.isArray(result.targets) ? result.targets : (result.target ? [result.target] : []);
  const end = result.end_error;
  if (end && Number.isFinite(end.position_error)) {
    const last = targets[lastIndex(targets)];
    let where = 'from the observation';
    if (last?.at_rest) where = 'from where it was seen lying';
    else if (last?.time != null) where = `from where it was seen at ${Number(last.time).toFixed(2)} s`;
    else if (last) where = 'from where it was seen moving';
    lines.push({ kind: 'end', text: `ends ${off(end)} ${where}` });
  }
  const rest = result.rest;
  if (rest) {
    if (rest.came_to_rest_s != null) {
      lines.push({ kind: 'info', text: `came to rest at ${Number(rest.came_to_rest_s).toFixed(2)} s` });
    } else {
      const need = rest.needs_duration_s == null ? ''
        : ` (it needs about ${Number(rest.needs_duration_s).toFixed(2)} s)`;
      lines.push({ kind: 'info', text: `still moving at the end${need}` });
    }
  }
  const rows = Array.isArray(result.observations) ? result.observations : [];
  if (rows.length > 1 || rows.some((r) => r.matched)) {
    for (const row of rows) {
      const time = row.target_time != null ? `${Number(row.target_time).toFixed(2)} s` : 'end';
      const how = [row.at_rest ? 'at rest' : (row.target_time == null ? 'seen moving' : null),
        row.angle_error_deg == null ? 'position only' : null].filter(Boolean).join(', ');
      lines.push({ kind: 'observation', text: `${time}${how ? ` (${how})` : ''}: ${off(row)}` });
      if (row.matched) {
        const at = Number(row.matched.time).toFixed(2);
        lines.push({ kind: 'observation', text: `  passes it at ${at} s: ${off(row.matched)}` });
      }
    }
  }
  for (const warning of result.warnings ?? []) lines.push({ kind: 'warning', text: String(warning) });
  return lines;
}
