// New objects in the scene (box, sphere, cylinder, or a mesh of the scene root with its packing,
// `GET /scenes`' `meshes`), from the panel's Add or the VR menu, and objects removed. A new object
// is movable; the objects table (or the VR menu) makes it fixed or the source.
import { buildObject, recolour } from './scene-view.js';
import { orbit, world } from './stage.js';
import { $, app, notify } from './state.js';

// The spawn list's choices: the primitives (10 cm), then the scene root's meshes.
const PRIMITIVES = {
  box: { shape: 'box', size: [0.1, 0.1, 0.1] },
  sphere: { shape: 'sphere', radius: 0.05 },
  cylinder: { shape: 'cylinder', radius: 0.04, height: 0.12 },
};
let meshes = []; // [{mesh, spheres}] paths inside the scene root

export function setMeshes(list) {
  meshes = Array.isArray(list) ? list : [];
  const select = $('spawn-kind');
  for (const opt of [...select.options]) if (opt.value.startsWith('mesh:')) opt.remove();
  for (const m of meshes) select.append(new Option(`mesh: ${m.mesh.split('/').pop()}`, `mesh:${m.mesh}`));
}

export const spawnChoices = () => [...Object.keys(PRIMITIVES), ...meshes.map((m) => `mesh:${m.mesh}`)];

// Where the panel's Add puts an object: under the point the camera looks at, 20 cm above the floor
// or at that point's height, whichever is higher.
export function defaultSpawnPosition() {
  const at = world.worldToLocal(orbit.target.clone());
  return [at.x, at.y, Math.max(0.2, at.z)];
}

// kind: 'box' | 'sphere' | 'cylinder' | 'mesh:<path in the scene root>'; position [x, y, z] in the
// scene. Returns the new object's id once it is drawn.
export async function spawnObject(kind, position = defaultSpawnPosition(), { fixed = false } = {}) {
  if (!app.model) throw new Error('load a scene first');
  let spec = PRIMITIVES[kind];
  if (!spec && kind.startsWith('mesh:')) {
    if (app.files) throw new Error('meshes of the scene root go into scenes of the scene root, not uploads');
    const path = kind.slice(5);
    const found = meshes.find((m) => m.mesh === path);
    spec = { mesh: path, spheres: found?.spheres ?? null };
  }
  if (!spec) throw new Error(`nothing to add called ${kind}: ${spawnChoices().join(', ')}`);
  const obj = app.model.addObject({ ...spec, position, fixed });
  await buildObject(obj);
  recolour();
  return obj.id;
}

export function removeObject(id) {
  app.model.removeObject(id);
  const node = app.nodes.get(id);
  node?.group.removeFromParent();
  app.nodes.delete(id);
  recolour();
  notify(`removed ${id}`);
}
