// The 3D view: cells as instanced cubes (one mesh per state), sensor poses as small axis
// frames, the box and ray tools' markers, picking. World frame, metres, z up.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { FREE, OCCUPIED, UNKNOWN } from './cells.js';

const BACKGROUND = 0xf3f4f6;
// Free and unknown cells are drawn smaller and see-through, so occupied ones stay readable.
const STYLE = {
  [OCCUPIED]: { shrink: 0.92, opacity: 1 },
  [FREE]: { shrink: 0.35, opacity: 0.25 },
  [UNKNOWN]: { shrink: 0.5, opacity: 0.35 },
};

function instancedMesh(state, capacity) {
  const { opacity } = STYLE[state];
  const material = new THREE.MeshLambertMaterial({ transparent: opacity < 1, opacity, depthWrite: opacity === 1 });
  const mesh = new THREE.InstancedMesh(new THREE.BoxGeometry(1, 1, 1), material, capacity);
  mesh.instanceColor = new THREE.InstancedBufferAttribute(new Float32Array(3 * capacity), 3);
  mesh.frustumCulled = false;
  mesh.count = 0;
  mesh.userData.state = state;
  mesh.userData.cellIndex = new Uint32Array(capacity);
  return mesh;
}

export class MapScene {
  constructor(canvas) {
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.05, 2000);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(-6, -8, 8);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener('change', () => this.requestRender());
    this.scene.add(new THREE.AmbientLight(0xffffff, 1.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(3, 5, 10);
    this.scene.add(sun);
    this.grid = new THREE.GridHelper(20, 20, 0xb0b4bb, 0xd5d8dd);
    this.grid.rotation.x = Math.PI / 2; // into the XY plane
    this.scene.add(this.grid);
    this.meshes = {};
    for (const s of [OCCUPIED, FREE, UNKNOWN]) this.setCapacity(s, 1024);
    this.poses = new THREE.Group();
    this.markers = new THREE.Group();
    this.scene.add(this.poses, this.markers);
    this.raycaster = new THREE.Raycaster();
    this.pending = false;
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  setCapacity(state, capacity) {
    const old = this.meshes[state];
    if (old) {
      this.scene.remove(old);
      old.geometry.dispose();
      old.material.dispose();
      old.dispose();
    }
    this.meshes[state] = instancedMesh(state, capacity);
    this.scene.add(this.meshes[state]);
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.canvas;
    if (w === 0 || h === 0) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.controls.update();
      const t0 = performance.now();
      this.renderer.render(this.scene, this.camera);
      this.renderMs = performance.now() - t0;
      if (this.onRender) this.onRender();
    });
  }

  // Looks at the map's extent from above and to the side.
  frame(extent) {
    const min = new THREE.Vector3(...extent.min);
    const max = new THREE.Vector3(...extent.max);
    const centre = min.clone().add(max).multiplyScalar(0.5);
    const radius = Math.max(1, max.clone().sub(min).length() / 2);
    this.controls.target.copy(centre);
    this.camera.position.copy(centre).add(new THREE.Vector3(-0.55, -0.95, 0.9).multiplyScalar(radius * 1.6));
    this.camera.far = radius * 50;
    this.camera.updateProjectionMatrix();
    const size = Math.ceil(Math.max(max.x - min.x, max.y - min.y) + 2);
    this.scene.remove(this.grid);
    this.grid = new THREE.GridHelper(size, size, 0xb0b4bb, 0xd5d8dd);
    this.grid.rotation.x = Math.PI / 2;
    this.grid.position.set(centre.x, centre.y, min.z);
    this.scene.add(this.grid);
    this.requestRender();
  }

  // Draws the cells of `flat` whose class (`classes[i]`) is shown, coloured by `colourOf(i)`
  // (writes r, g, b into the given array at the given offset).
  setCells(flat, classes, shown, colourOf) {
    for (const state of [OCCUPIED, FREE, UNKNOWN]) {
      let count = 0;
      if (shown[state]) for (let i = 0; i < flat.n; i++) if (classes[i] === state) count++;
      if (count > this.meshes[state].instanceMatrix.count) this.setCapacity(state, Math.ceil(count * 1.5));
      const mesh = this.meshes[state];
      const m = mesh.instanceMatrix.array;
      const c = mesh.instanceColor.array;
      const shrink = STYLE[state].shrink;
      let k = 0;
      for (let i = 0; shown[state] && i < flat.n; i++) {
        if (classes[i] !== state) continue;
        const s = flat.sizes[i] * shrink;
        m.fill(0, 16 * k, 16 * k + 16);
        m[16 * k] = m[16 * k + 5] = m[16 * k + 10] = s;
        m[16 * k + 12] = flat.centres[3 * i];
        m[16 * k + 13] = flat.centres[3 * i + 1];
        m[16 * k + 14] = flat.centres[3 * i + 2];
        m[16 * k + 15] = 1;
        colourOf(i, c, 3 * k);
        mesh.userData.cellIndex[k] = i;
        k++;
      }
      mesh.count = k;
      mesh.instanceMatrix.needsUpdate = true;
      mesh.instanceColor.needsUpdate = true;
      mesh.boundingSphere = null;
      mesh.boundingBox = null;
    }
    this.requestRender();
  }

  drawnCount() {
    return Object.values(this.meshes).reduce((n, m) => n + m.count, 0);
  }

  // Sensor poses as small RGB = xyz axis frames.
  setPoses(poses) {
    this.poses.clear();
    for (const p of poses) {
      const frame = new THREE.AxesHelper(0.35);
      const [w, x, y, z] = p.rotation;
      frame.position.set(...p.translation);
      frame.quaternion.set(x, y, z, w);
      this.poses.add(frame);
    }
    this.requestRender();
  }

  ndc(clientX, clientY) {
    const r = this.canvas.getBoundingClientRect();
    return new THREE.Vector2(((clientX - r.left) / r.width) * 2 - 1, -((clientY - r.top) / r.height) * 2 + 1);
  }

  // The nearest drawn cell under the pointer: its index in the drawn data and the hit point.
  pickCell(clientX, clientY) {
    this.raycaster.setFromCamera(this.ndc(clientX, clientY), this.camera);
    const meshes = Object.values(this.meshes).filter((m) => m.count > 0);
    const hit = this.raycaster.intersectObjects(meshes, false)[0];
    if (!hit || hit.instanceId === undefined) return null;
    return { index: hit.object.userData.cellIndex[hit.instanceId], point: hit.point.toArray() };
  }

  // Where the pointer meets the horizontal plane at height z.
  pointOnPlane(clientX, clientY, z) {
    this.raycaster.setFromCamera(this.ndc(clientX, clientY), this.camera);
    const plane = new THREE.Plane(new THREE.Vector3(0, 0, 1), -z);
    const out = new THREE.Vector3();
    return this.raycaster.ray.intersectPlane(plane, out) ? out.toArray() : null;
  }

  // Page coordinates of a world point (for tests and tools).
  project(p) {
    const v = new THREE.Vector3(...p).project(this.camera);
    const r = this.canvas.getBoundingClientRect();
    return { x: r.left + ((v.x + 1) / 2) * r.width, y: r.top + ((1 - v.y) / 2) * r.height, visible: v.z < 1 };
  }

  clearMarkers() {
    this.markers.clear();
    this.requestRender();
  }

  showBox(min, max) {
    const box = new THREE.Box3(new THREE.Vector3(...min), new THREE.Vector3(...max));
    this.markers.add(new THREE.Box3Helper(box, 0xd9480f));
    this.requestRender();
  }

  showRay(from, to, hit) {
    const line = new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(...from), new THREE.Vector3(...to)]);
    this.markers.add(new THREE.Line(line, new THREE.LineBasicMaterial({ color: 0x1c7ed6 })));
    if (hit) {
      const dot = new THREE.Mesh(new THREE.SphereGeometry(0.08), new THREE.MeshBasicMaterial({ color: 0xe03131 }));
      dot.position.set(...hit);
      this.markers.add(dot);
    }
    this.requestRender();
  }

  target() {
    return this.controls.target.toArray();
  }
}
