// Three.js geometry for scene objects: primitives, meshes (OBJ, STL, PLY, GLB) and sphere packings.
import * as THREE from 'three';
import { OBJLoader } from 'three/addons/loaders/OBJLoader.js';
import { STLLoader } from 'three/addons/loaders/STLLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { serverFetch } from './connection.js';

const PLANE_SIZE = 12; // metres: the infinite plane z = 0, drawn as a square

export function primitiveGeometry(obj) {
  switch (obj.shape) {
    case 'plane':
      return new THREE.PlaneGeometry(PLANE_SIZE, PLANE_SIZE);
    case 'box':
      return new THREE.BoxGeometry(...obj.size);
    case 'sphere':
      return new THREE.SphereGeometry(obj.radius, 32, 16);
    case 'cylinder': {
      const g = new THREE.CylinderGeometry(obj.radius, obj.radius, obj.height, 32);
      g.rotateX(Math.PI / 2); // three's cylinders run along y, the scene's along z
      return g;
    }
    default:
      throw new Error(`object ${obj.id}: unknown shape ${obj.shape}`);
  }
}

function extension(name) {
  const m = /\.([A-Za-z0-9]+)$/.exec(name.split('?')[0]);
  return m ? m[1].toLowerCase() : '';
}

// A mesh file as one Object3D whose meshes all use `material`. name decides the loader.
export async function loadMesh(url, name, material) {
  const ext = extension(name);
  const response = await serverFetch(url);
  if (!response.ok) throw new Error(`${name}: HTTP ${response.status}`);
  let node;
  if (ext === 'obj') {
    node = new OBJLoader().parse(await response.text());
  } else if (ext === 'stl') {
    node = new THREE.Mesh(new STLLoader().parse(await response.arrayBuffer()));
  } else if (ext === 'ply') {
    node = new THREE.Mesh(new PLYLoader().parse(await response.arrayBuffer()));
  } else if (ext === 'glb' || ext === 'gltf') {
    const gltf = await new GLTFLoader().parseAsync(await response.arrayBuffer(), '');
    node = gltf.scene;
  } else {
    throw new Error(`${name}: no loader for .${ext} meshes`);
  }
  node.traverse((m) => {
    if (m.isMesh) {
      if (!m.geometry.attributes.normal) m.geometry.computeVertexNormals();
      m.material = material;
    }
  });
  return node;
}

// A .spheres file (`x y z r` per line, `#` comments) as instanced spheres in the object's frame.
export function parseSpheres(text) {
  const spheres = [];
  for (const line of text.split('\n')) {
    const t = line.trim();
    if (!t || t.startsWith('#')) continue;
    const v = t.split(/\s+/).map(Number);
    if (v.length >= 4 && v.every(Number.isFinite)) spheres.push(v.slice(0, 4));
  }
  return spheres;
}

export function spheresMesh(spheres, color) {
  const material = new THREE.MeshStandardMaterial({ color, transparent: true, opacity: 0.45 });
  const mesh = new THREE.InstancedMesh(new THREE.SphereGeometry(1, 12, 8), material, spheres.length);
  const m = new THREE.Matrix4();
  spheres.forEach(([x, y, z, r], i) => {
    m.makeScale(r, r, r).setPosition(x, y, z);
    mesh.setMatrixAt(i, m);
  });
  mesh.userData.spherePacking = true;
  return mesh;
}
