// The mesh viewer: three.js (vendored in /static/vendor/three), orbit/zoom/pan, lighting
// from vertex normals, an up-axis choice, inferred faces shown, dimmed or hidden, and the
// scans' poses (pinhole cameras as frusta, other sensors as origins). It renders on demand:
// only when the camera or the content changes.
import * as THREE from "three";
import { OrbitControls } from "three/addons/OrbitControls.js";

const BACKGROUND = 0xf4f5f7;
const MEASURED = 0x8fb3d9;
const INFERRED = 0xb9b9b9;

// Rotations that bring the scene's up axis onto three.js's +Y.
const UP = {
  z: new THREE.Euler(-Math.PI / 2, 0, 0),
  y: new THREE.Euler(0, 0, 0),
  x: new THREE.Euler(0, 0, Math.PI / 2),
  "-y": new THREE.Euler(Math.PI, 0, 0),
  "-z": new THREE.Euler(Math.PI / 2, 0, 0),
};

// The preview file (service/previews.py): one or two levels (the preview, then a coarse
// level drawn while the camera moves), each "RFPV0001", 4 uint32, float32 positions, uint32
// indices with the measured faces first.
export function decodePreview(buf) {
  const levels = [];
  let o = 0;
  while (o < buf.byteLength) {
    const magic = new TextDecoder().decode(new Uint8Array(buf, o, 8));
    if (magic !== "RFPV0001") throw new Error("the preview is not in the expected format");
    const [nv, nf, nMeasured, sourceFaces] = new Uint32Array(buf, o + 8, 4);
    levels.push({
      positions: new Float32Array(buf, o + 24, nv * 3),
      indices: new Uint32Array(buf, o + 24 + nv * 12, nf * 3),
      nFaces: nf, nMeasured, sourceFaces, normals: null,
    });
    o += 24 + nv * 12 + nf * 12;
  }
  return { ...levels[0], coarse: levels[1] || null };
}

const PLY_TYPES = {
  char: ["getInt8", 1], int8: ["getInt8", 1], uchar: ["getUint8", 1], uint8: ["getUint8", 1],
  short: ["getInt16", 2], int16: ["getInt16", 2], ushort: ["getUint16", 2], uint16: ["getUint16", 2],
  int: ["getInt32", 4], int32: ["getInt32", 4], uint: ["getUint32", 4], uint32: ["getUint32", 4],
  float: ["getFloat32", 4], float32: ["getFloat32", 4], double: ["getFloat64", 8], float64: ["getFloat64", 8],
};

// A binary little-endian PLY of triangles (the service's /mesh?format=ply), with the face
// property "inferred" when present; faces reordered measured first, like the preview.
export function parsePly(buf) {
  const bytes = new Uint8Array(buf);
  const text = new TextDecoder("latin1").decode(bytes.subarray(0, Math.min(bytes.length, 8192)));
  const end = text.indexOf("end_header\n");
  if (!text.startsWith("ply") || end < 0) throw new Error("not a PLY file");
  if (!/format binary_little_endian/.test(text)) throw new Error("only binary little-endian PLY is supported");
  const elements = [];
  for (const line of text.slice(0, end).split("\n")) {
    const w = line.trim().split(/\s+/);
    if (w[0] === "element") elements.push({ name: w[1], count: +w[2], props: [] });
    else if (w[0] === "property") elements.at(-1).props.push(w[1] === "list"
      ? { list: true, count: PLY_TYPES[w[2]], item: PLY_TYPES[w[3]], name: w[4] }
      : { type: PLY_TYPES[w[1]], name: w[2] });
  }
  const dv = new DataView(buf);
  let o = end + "end_header\n".length;
  let positions = null, normals = null, faces = null, inferred = null;
  for (const el of elements) {
    if (el.name === "vertex") {
      positions = new Float32Array(el.count * 3);
      const ix = ["x", "y", "z"].map(n => el.props.findIndex(p => p.name === n));
      const inn = ["nx", "ny", "nz"].map(n => el.props.findIndex(p => p.name === n));
      if (inn.every(i => i >= 0)) normals = new Float32Array(el.count * 3);
      const offs = []; let stride = 0;
      for (const p of el.props) { offs.push(stride); stride += p.type[1]; }
      for (let v = 0; v < el.count; v++, o += stride) {
        for (let a = 0; a < 3; a++) {
          const p = el.props[ix[a]];
          positions[3 * v + a] = dv[p.type[0]](o + offs[ix[a]], true);
          if (normals) normals[3 * v + a] = dv[el.props[inn[a]].type[0]](o + offs[inn[a]], true);
        }
      }
    } else if (el.name === "face") {
      faces = new Uint32Array(el.count * 3);
      inferred = new Uint8Array(el.count);
      for (let f = 0; f < el.count; f++) {
        for (const p of el.props) {
          if (p.list) {
            const n = dv[p.count[0]](o, true); o += p.count[1];
            if (n !== 3) throw new Error("only triangle meshes are supported");
            for (let k = 0; k < 3; k++) faces[3 * f + k] = dv[p.item[0]](o + k * p.item[1], true);
            o += 3 * p.item[1];
          } else {
            if (p.name === "inferred") inferred[f] = dv[p.type[0]](o, true);
            o += p.type[1];
          }
        }
      }
    } else {
      throw new Error(`unexpected PLY element ${el.name}`);
    }
  }
  let nMeasured = 0;
  for (let f = 0; f < inferred.length; f++) if (!inferred[f]) nMeasured++;
  const indices = new Uint32Array(faces.length);
  let a = 0, b = nMeasured;
  for (let f = 0; f < inferred.length; f++) {
    const dst = inferred[f] ? b++ : a++;
    indices[3 * dst] = faces[3 * f]; indices[3 * dst + 1] = faces[3 * f + 1]; indices[3 * dst + 2] = faces[3 * f + 2];
  }
  return { positions, indices, normals, nFaces: inferred.length, nMeasured, sourceFaces: inferred.length };
}

// A vertex whose faces' normals cancel out (a fold left by simplification) has no normal,
// and a zero normal lights as black: it takes the normal of one of its faces instead.
function fixZeroNormals(g) {
  const n = g.attributes.normal.array, p = g.attributes.position.array, idx = g.index.array;
  for (let f = 0; f < idx.length; f += 3) {
    for (let k = 0; k < 3; k++) {
      const v = idx[f + k];
      if (n[3 * v] * n[3 * v] + n[3 * v + 1] * n[3 * v + 1] + n[3 * v + 2] * n[3 * v + 2] > 0.25) continue;
      const [a, b, c] = [idx[f], idx[f + 1], idx[f + 2]];
      const ux = p[3 * b] - p[3 * a], uy = p[3 * b + 1] - p[3 * a + 1], uz = p[3 * b + 2] - p[3 * a + 2];
      const wx = p[3 * c] - p[3 * a], wy = p[3 * c + 1] - p[3 * a + 1], wz = p[3 * c + 2] - p[3 * a + 2];
      const nx = uy * wz - uz * wy, ny = uz * wx - ux * wz, nz = ux * wy - uy * wx;
      const len = Math.hypot(nx, ny, nz);
      if (len > 0) { n[3 * v] = nx / len; n[3 * v + 1] = ny / len; n[3 * v + 2] = nz / len; }
    }
  }
}

export class Viewer {
  constructor(container) {
    this.container = container;
    this.renderer = new THREE.WebGLRenderer({ antialias: false, powerPreference: "high-performance" });
    this.renderer.setPixelRatio(1);  // software WebGL: device pixels cost frames (0.5 moving)
    this.renderer.setClearColor(BACKGROUND);
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.root = new THREE.Group();  // the world, rotated so the chosen axis is up
    this.scene.add(this.root);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.01, 1000);
    this.scene.add(this.camera);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.2));
    const headlight = new THREE.DirectionalLight(0xffffff, 1.6);
    headlight.position.set(0.4, 0.6, 1);  // follows the camera
    this.camera.add(headlight);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    // The camera moves (a drag, the wheel, keys): the coarse level until it has been still
    // for 200 ms, then the mesh once.
    this.moving = false;
    this.lod = true;  // draw the coarse level while moving
    this.controls.addEventListener("change", () => {
      this.moving = true;
      clearTimeout(this.still);
      this.still = setTimeout(() => { this.moving = false; this.requestRender(); }, 200);
      this.requestRender();
    });
    // Smooth shading from vertex normals; flat shading (each face's own normal, facing the
    // camera) for simplified levels, whose folds make vertex normals unreliable.
    const pair = flatShading => [MEASURED, INFERRED].map(color =>
      new THREE.MeshLambertMaterial({ color, side: THREE.DoubleSide, flatShading }));
    this.materials = { smooth: pair(false), flat: pair(true) };
    this.mesh = null;
    this.coarse = null;
    this.poses = null;
    this.inferredMode = "dim";
    this.frames = 0;
    this.pending = false;
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
  }

  resize() {
    const w = this.container.clientWidth || 800, h = this.container.clientHeight || 600;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.requestRender();
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  render() {
    const light = this.moving && this.lod;  // while the camera moves (docs/webapp.md):
    if (this.coarse) {  // the coarse level
      this.coarse.visible = light;
      this.mesh.visible = !light;
    }
    const ratio = light ? 0.5 : 1;  // and half the pixels on each axis
    if (this.renderer.getPixelRatio() !== ratio) {
      this.renderer.setPixelRatio(ratio);
      this.renderer.setSize(this.container.clientWidth || 800, this.container.clientHeight || 600, false);
    }
    this.renderer.render(this.scene, this.camera);
    this.frames++;
  }

  clear() {
    for (const m of [this.mesh, this.coarse]) if (m) { this.root.remove(m); m.geometry.dispose(); }
    this.mesh = this.coarse = null;
    this.requestRender();
  }

  _build(data, flat) {
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(data.positions, 3));
    g.setIndex(new THREE.BufferAttribute(data.indices, 1));
    if (data.normals) g.setAttribute("normal", new THREE.BufferAttribute(data.normals, 3));
    else if (!flat) { g.computeVertexNormals(); fixZeroNormals(g); }
    const nIdx = data.indices.length, m = data.nMeasured * 3;
    if (m > 0) g.addGroup(0, m, 0);
    if (nIdx > m) g.addGroup(m, nIdx - m, 1);
    g.computeBoundingSphere();
    const mesh = new THREE.Mesh(g, flat ? this.materials.flat : this.materials.smooth);
    this.root.add(mesh);
    return mesh;
  }

  // data: {positions, indices, normals?, nMeasured} (decodePreview or parsePly); coarse:
  // a lighter level of the same surface, drawn instead while the camera moves.
  setMesh(data, { keepView = false, coarse = null } = {}) {
    this.clear();
    this.mesh = this._build(data, data.nFaces < data.sourceFaces);
    this.coarse = coarse ? this._build(coarse, true) : null;
    this.setInferred(this.inferredMode);
    if (!keepView) this.fit();
    this.requestRender();
  }

  setInferred(mode) {
    this.inferredMode = mode;
    for (const mat of [this.materials.smooth[1], this.materials.flat[1]]) {
      mat.visible = mode !== "hide";
      mat.transparent = mode === "dim";
      mat.opacity = mode === "dim" ? 0.25 : 1;
      mat.depthWrite = mode !== "dim";
      mat.needsUpdate = true;
    }
    this.requestRender();
  }

  setUp(axis) {
    this.root.rotation.copy(UP[axis] || UP.z);
    this.root.updateMatrixWorld(true);
    this.fit();
  }

  // The scans' poses: pinhole cameras as frusta, the others as their origins (with axes).
  setPoses(placements, show) {
    if (this.poses) { this.root.remove(this.poses); this.poses.traverse(o => o.geometry?.dispose()); }
    this.poses = new THREE.Group();
    const size = this.mesh ? this.mesh.geometry.boundingSphere.radius * 0.15 : 0.2;
    const lines = [], origins = [];
    const m = new THREE.Matrix4(), p = new THREE.Vector3();
    const at = (x, y, z) => p.set(x, y, z).applyMatrix4(m).toArray();
    for (const s of placements) {
      m.set(...s.pose.flat());
      const o = at(0, 0, 0);
      origins.push(...o);
      if (s.sensor.model === "pinhole") {
        const { width: w, height: h, fx, fy, cx, cy } = s.sensor;
        const corners = [[0, 0], [w, 0], [w, h], [0, h]].map(([u, v]) => at((u - cx) / fx * size, (v - cy) / fy * size, size));
        for (let i = 0; i < 4; i++) lines.push(...o, ...corners[i], ...corners[i], ...corners[(i + 1) % 4]);
        lines.push(...at(0, -cy / fy * size, size), ...at(0, -cy / fy * size * 1.4, size));  // image up
      } else {
        for (const axis of [[1, 0, 0], [0, 1, 0], [0, 0, 1]]) lines.push(...o, ...at(...axis.map(c => c * size)));
      }
    }
    const lg = new THREE.BufferGeometry();
    lg.setAttribute("position", new THREE.Float32BufferAttribute(lines, 3));
    this.poses.add(new THREE.LineSegments(lg, new THREE.LineBasicMaterial({ color: 0xd2691e })));
    const pg = new THREE.BufferGeometry();
    pg.setAttribute("position", new THREE.Float32BufferAttribute(origins, 3));
    this.poses.add(new THREE.Points(pg, new THREE.PointsMaterial({ color: 0xb03a00, size: 6, sizeAttenuation: false })));
    this.poses.visible = show;
    this.root.add(this.poses);
    this.requestRender();
  }

  showPoses(show) { if (this.poses) this.poses.visible = show; this.requestRender(); }

  // World-space bounding sphere of what is shown (the mesh, else the poses).
  bounds() {
    const box = new THREE.Box3();
    if (this.mesh) box.setFromObject(this.mesh);
    else if (this.poses) box.setFromObject(this.poses);
    if (box.isEmpty()) return null;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    if (!this.mesh) sphere.radius = Math.max(sphere.radius, 1);  // poses alone: a metre around
    return sphere;
  }

  fit() {
    this.root.updateMatrixWorld(true);
    const s = this.bounds();
    if (!s) { this.requestRender(); return; }
    const r = Math.max(s.radius, 1e-3);
    const d = r / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2)) * 1.05;
    const dir = new THREE.Vector3(0.9, 0.55, 1.1).normalize();
    this.camera.position.copy(s.center).addScaledVector(dir, d);
    this.camera.near = Math.max(d / 1000, r / 1000);
    this.camera.far = d + 4 * r;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(s.center);
    this.controls.update();
    this.requestRender();
  }

  // Pixels of the canvas right after a render (no preserveDrawingBuffer needed): how many
  // differ from the background, and a checksum, on a downscaled copy.
  pixelStats(size = 256) {
    const moving = this.moving;
    this.moving = false;  // the mesh at rest
    this.render();
    this.moving = moving;
    const c = document.createElement("canvas");
    c.width = size; c.height = size;
    const ctx = c.getContext("2d", { willReadFrequently: true });
    ctx.drawImage(this.renderer.domElement, 0, 0, size, size);
    const px = ctx.getImageData(0, 0, size, size).data;
    const [br, bg_, bb] = [(BACKGROUND >> 16) & 255, (BACKGROUND >> 8) & 255, BACKGROUND & 255];
    let nonBackground = 0, sum = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - br) + Math.abs(px[i + 1] - bg_) + Math.abs(px[i + 2] - bb) > 6) nonBackground++;
      sum = (sum * 31 + px[i] + 7 * px[i + 1] + 13 * px[i + 2]) >>> 0;
    }
    return { nonBackground, total: size * size, checksum: sum };
  }

  // Orbit the camera around its target for `seconds`, one step per animation frame, and
  // count the frames drawn (benchmarks/viewer_fps.py). lod: draw the coarse level while
  // moving, as when a person drags.
  orbit(seconds = 5, lod = true) {
    return new Promise(resolve => {
      const target = this.controls.target.clone();
      const offset = this.camera.position.clone().sub(target);
      const axis = new THREE.Vector3(0, 1, 0);
      const savedLod = this.lod;
      this.lod = lod; this.moving = true;
      let frames = 0, t0 = null;
      const step = now => {
        if (t0 === null) t0 = now;
        offset.applyAxisAngle(axis, 0.02);
        this.camera.position.copy(target).add(offset);
        this.camera.lookAt(target);
        this.render();
        frames++;
        if (now - t0 < seconds * 1000) { requestAnimationFrame(step); return; }
        const drawn = this.coarse && this.coarse.visible ? this.coarse : this.mesh;
        this.lod = savedLod; this.moving = false; this.requestRender();
        resolve({ frames, seconds: (now - t0) / 1000, fps: frames / ((now - t0) / 1000),
                  faces: drawn ? drawn.geometry.index.count / 3 : 0 });
      };
      requestAnimationFrame(step);
    });
  }
}
