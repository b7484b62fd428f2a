// trisplat viewer: the mesh, orbit and walk controls, training cameras as frusta, and a toggle between the mesh and
// the ground-truth photo seen from the nearest camera. Data comes from the local server: /api/scene.json (counts,
// bounds, up, cameras) and either /api/mesh.glb (a glTF file, loaded by three.js's GLTFLoader with the materials,
// textures and colour spaces it defines: what an engine shows) or /api/mesh.bin (float32 positions | uint8 sRGB
// colours | uint32 faces). Colour: three.js's linear working space, sRGB output, no tone mapping.
import {
  AmbientLight, BufferAttribute, BufferGeometry, Color, DirectionalLight, DoubleSide, Float32BufferAttribute,
  GLTFLoader, Group, LineBasicMaterial, LineSegments, Matrix4, Mesh, MeshBasicMaterial, MeshLambertMaterial,
  NoToneMapping, OrbitControls, PerspectiveCamera, Quaternion, SRGBColorSpace, Scene, Vector3, WebGLRenderer,
} from './three.bundle.min.js';

const BACKGROUND = 0x202428;
const FRUSTUM_COLOR = 0xd0a040;
const SELECTED_COLOR = 0x40e0ff;
const FRUSTUM_SIZE = 0.12;     // frustum depth as a fraction of the median camera distance to the mesh centre
const OVERVIEW_FIT = 1.3;      // the first view frames the mesh's bounding sphere with this margin
const WALK_SPEED = 0.4;        // scene radii per second (x4 with Shift)
const LOOK_SPEED = 0.004;      // radians per pixel dragged in walk mode
const DIRECTION_WEIGHT = 1.0;  // nearest camera: distance in radii + this * (1 - cos(angle between view directions))

const params = new URLSearchParams(location.search);
if (params.get('clean') === '1') document.body.classList.add('clean');
const stage = document.getElementById('stage');
const photo = document.getElementById('photo');
const statusEl = document.getElementById('status');

// glTF: base colour textures are sRGB, COLOR_0 linear; three.js works in linear light and encodes to sRGB on output
// (hex colours below are sRGB display values, converted by ColorManagement on the way in).
const renderer = new WebGLRenderer({ antialias: true });
renderer.outputColorSpace = SRGBColorSpace;
renderer.toneMapping = NoToneMapping;
renderer.setPixelRatio(window.devicePixelRatio || 1);
stage.appendChild(renderer.domElement);
const scene = new Scene();
scene.background = new Color(BACKGROUND);
const camera = new PerspectiveCamera(50, 1, 0.01, 100);
let controls = null; // made once the scene's up direction is known (OrbitControls fixes it at construction)

const state = {
  info: null, cams: [], radius: 1, extent: 1, frustumDepth: 0.1, up: new Vector3(0, 1, 0), mesh: null, frusta: null, selected: null,
  snapped: null, showPhoto: false, walk: false, shaded: false, keys: new Set(), dirty: true, lastTime: 0,
};
let lights = null;

function setStatus() {
  const i = state.info;
  if (!i) return;
  let s = `${i.num_faces.toLocaleString()} faces, ${i.num_vertices.toLocaleString()} vertices, ${i.cameras.length} cameras`;
  if (state.snapped !== null) {
    const cam = state.cams[state.snapped];
    s += `\nat ${cam.split === 'test' ? 'test camera ' : ''}${cam.name}: showing ${state.showPhoto ? 'ground-truth photo' : 'mesh'}`;
  }
  s += `\nmode: ${state.walk ? 'walk' : 'orbit'}`;
  statusEl.textContent = s;
  document.getElementById('btn-orbit').classList.toggle('on', !state.walk);
  document.getElementById('btn-walk').classList.toggle('on', state.walk);
  document.getElementById('btn-photo').classList.toggle('on', state.showPhoto);
  document.getElementById('btn-shade').classList.toggle('on', state.shaded);
  document.getElementById('btn-frusta').classList.toggle('on', !!(state.frusta && state.frusta.visible));
}

// ---- cameras -----------------------------------------------------------------------------------------------
function c2wMatrix(cam) { return new Matrix4().set(...cam.c2w); } // OpenGL axes, row-major from the server

function frustumPoints(cam, depth) {
  // apex and the four image corners at `depth` (pixel corners, OpenCV intrinsics), in world coordinates
  const K = cam.K, m = c2wMatrix(cam);
  const corners = [[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]].map(([u, v]) => {
    const x = (u - K[2]) / K[0], y = (v - K[5]) / K[4];
    return new Vector3(x * depth, -y * depth, -depth).applyMatrix4(m); // OpenCV (x, y, 1) -> OpenGL (x, -y, -1)
  });
  const apex = new Vector3().setFromMatrixPosition(m);
  const top = new Vector3(0, (K[5] / K[4]) * depth * 1.3, -depth).applyMatrix4(m); // marks the image's up side
  return { apex, corners, top };
}

function frustumSegments(cams, depth) {
  const p = [];
  for (const cam of cams) {
    const { apex, corners, top } = frustumPoints(cam, depth);
    for (let k = 0; k < 4; k++) {
      p.push(apex, corners[k], corners[k], corners[(k + 1) % 4]);
    }
    p.push(corners[0], top, top, corners[1]);
  }
  return new Float32BufferAttribute(p.flatMap((v) => [v.x, v.y, v.z]), 3);
}

function buildFrusta() {
  const cams = state.info.cameras;
  if (!cams.length) return;
  const g = new BufferGeometry();
  g.setAttribute('position', frustumSegments(cams, state.frustumDepth));
  state.frusta = new LineSegments(g, new LineBasicMaterial({ color: FRUSTUM_COLOR }));
  scene.add(state.frusta);
  const sg = new BufferGeometry();
  sg.setAttribute('position', frustumSegments([cams[0]], state.frustumDepth));
  state.selected = new LineSegments(sg, new LineBasicMaterial({ color: SELECTED_COLOR }));
  state.selected.visible = false;
  scene.add(state.selected);
}

function highlight(index) {
  if (!state.selected) return;
  state.selected.geometry.setAttribute('position', frustumSegments([state.cams[index]], state.frustumDepth * 1.02));
  state.selected.visible = state.frusta.visible;
}

function nearestCamera() {
  const eye = camera.getWorldPosition(new Vector3());
  const dir = camera.getWorldDirection(new Vector3());
  let best = null, bestScore = Infinity;
  state.info.cameras.forEach((cam, i) => {
    const m = c2wMatrix(cam);
    const c = new Vector3().setFromMatrixPosition(m);
    const f = new Vector3(0, 0, -1).transformDirection(m);
    const score = c.distanceTo(eye) / state.radius + DIRECTION_WEIGHT * (1 - f.dot(dir));
    if (score < bestScore) { bestScore = score; best = i; }
  });
  return best;
}

function projectionFromK(cam, near, far) {
  // pixel (u, v) with corners at integers maps to NDC x = 2u/W - 1, y = 1 - 2v/H (docs/conventions.md)
  const K = cam.K, W = cam.width, H = cam.height;
  return new Matrix4().set(
    2 * K[0] / W, 0, 1 - 2 * K[2] / W, 0,
    0, 2 * K[4] / H, 2 * K[5] / H - 1, 0,
    0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, -1, 0,
  );
}

function trainIndex(index) { // wraps around the training cameras
  const n = state.info.cameras.length;
  return ((index % n) + n) % n;
}

function snapTo(index, showPhoto) {
  // index into state.cams: the training cameras, then the test cameras. The view becomes that camera exactly:
  // its pose, and a projection made from its intrinsics (principal point included) on a canvas of its aspect.
  const cam = state.cams[index];
  if (!cam) return;
  state.snapped = index;
  const m = c2wMatrix(cam);
  m.decompose(camera.position, camera.quaternion, new Vector3());
  camera.updateMatrixWorld(true);
  const fwd = new Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
  const toCentre = Math.max(new Vector3().sub(camera.position).dot(fwd), 0.1 * state.radius);
  controls.target.copy(camera.position).addScaledVector(fwd, toCentre);
  highlight(index);
  setPhoto(showPhoto);
  layout();
}

function unsnap() {
  if (state.snapped === null) return;
  const cam = state.cams[state.snapped];
  state.snapped = null;
  camera.fov = (2 * Math.atan(cam.height / (2 * cam.K[4])) * 180) / Math.PI;
  setPhoto(false);
  layout();
}

function setPhoto(show) {
  state.showPhoto = !!show && state.snapped !== null && state.cams[state.snapped].has_image;
  if (state.showPhoto) {
    const src = `/api/image/${state.snapped}.png`;
    if (!photo.src.endsWith(src)) { photo.dataset.loaded = ''; photo.src = src; }
    photo.style.display = 'block';
  } else {
    photo.style.display = 'none';
  }
  state.dirty = true;
  setStatus();
}

// ---- layout and rendering -------------------------------------------------------------------------------
function layout() {
  const W = window.innerWidth, H = window.innerHeight;
  let w = W, h = H, left = 0, top = 0;
  if (state.snapped !== null) { // letterbox to the photo's aspect so mesh and photo line up pixel for pixel
    const cam = state.cams[state.snapped];
    const s = Math.min(W / cam.width, H / cam.height);
    w = Math.round(cam.width * s); h = Math.round(cam.height * s);
    left = Math.floor((W - w) / 2); top = Math.floor((H - h) / 2);
  }
  renderer.setSize(w, h);
  for (const el of [renderer.domElement, photo]) {
    el.style.left = `${left}px`; el.style.top = `${top}px`; el.style.width = `${w}px`; el.style.height = `${h}px`;
  }
  const near = 0.002 * state.radius, far = 20 * state.extent;
  if (state.snapped !== null) {
    camera.projectionMatrix.copy(projectionFromK(state.cams[state.snapped], near, far));
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  } else {
    camera.aspect = w / h; camera.near = near; camera.far = far;
    camera.updateProjectionMatrix();
  }
  state.dirty = true;
  if (document.body.dataset.ready === '1') window.trisplatReport({ kind: 'layout', canvas: [w, h] }); // resized later
}

function setShaded(on) {
  // shaded: each mesh's own colours (texture, vertex colours, factor) under a Lambert material with two lights;
  // off: the material the mesh came with (the GLB's unlit material, or unlit vertex colours)
  state.shaded = on;
  if (on && !lights) {
    lights = [new AmbientLight(0xffffff, 0.55), new DirectionalLight(0xffffff, 0.9)];
    lights[1].position.copy(state.up).multiplyScalar(3 * state.radius).add(new Vector3(state.radius, 0, state.radius));
    scene.add(...lights);
  }
  state.mesh.traverse((o) => {
    if (!o.isMesh) return;
    const d = o.userData;
    if (!d.basic) d.basic = o.material;
    if (on && !d.shaded) {
      if (!o.geometry.getAttribute('normal')) o.geometry.computeVertexNormals();
      const b = d.basic;
      d.shaded = new MeshLambertMaterial({
        color: b.color, map: b.map, vertexColors: b.vertexColors, side: DoubleSide, flatShading: true,
      });
    }
    o.material = on ? d.shaded : d.basic;
  });
  state.dirty = true;
  setStatus();
}

function walkStep(dt) {
  if (!state.walk || state.keys.size === 0) return;
  const up = state.up;
  const fwd = camera.getWorldDirection(new Vector3());
  fwd.addScaledVector(up, -fwd.dot(up));
  if (fwd.lengthSq() < 1e-8) fwd.set(0, 0, -1).applyQuaternion(camera.quaternion);
  fwd.normalize();
  const right = new Vector3().crossVectors(fwd, up).normalize();
  const speed = WALK_SPEED * state.radius * dt * (state.keys.has('shift') ? 4 : 1);
  const move = new Vector3();
  if (state.keys.has('w')) move.add(fwd);
  if (state.keys.has('s')) move.sub(fwd);
  if (state.keys.has('d')) move.add(right);
  if (state.keys.has('a')) move.sub(right);
  if (state.keys.has('e')) move.add(up);
  if (state.keys.has('q')) move.sub(up);
  if (move.lengthSq() === 0) return;
  unsnap();
  move.normalize().multiplyScalar(speed);
  camera.position.add(move);
  controls.target.add(move);
  state.dirty = true;
}

function frame(time) {
  const dt = Math.min((time - state.lastTime) / 1000, 0.1);
  state.lastTime = time;
  walkStep(dt);
  if (state.dirty) {
    state.dirty = false;
    renderer.render(scene, camera);
  }
  requestAnimationFrame(frame);
}

// ---- input ------------------------------------------------------------------------------------------------
function setWalk(on) {
  state.walk = on;
  controls.enabled = !on;
  if (!on) { // orbit around the point in front of the camera
    const fwd = camera.getWorldDirection(new Vector3());
    const d = Math.max(controls.target.distanceTo(camera.position), 0.1 * state.radius);
    controls.target.copy(camera.position).addScaledVector(fwd, d);
  }
  setStatus();
}

function makeControls() {
  controls = new OrbitControls(camera, renderer.domElement);
  controls.addEventListener('start', () => unsnap());
  controls.addEventListener('change', () => { state.dirty = true; });
}

let drag = null;
renderer.domElement.addEventListener('pointerdown', (e) => { if (state.walk) drag = { x: e.clientX, y: e.clientY }; });
window.addEventListener('pointerup', () => { drag = null; });
window.addEventListener('pointermove', (e) => {
  if (!state.walk || !drag) return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  drag = { x: e.clientX, y: e.clientY };
  unsnap();
  const yaw = new Quaternion().setFromAxisAngle(state.up, -dx * LOOK_SPEED);
  const right = new Vector3(1, 0, 0).applyQuaternion(camera.quaternion);
  const pitch = new Quaternion().setFromAxisAngle(right, -dy * LOOK_SPEED);
  camera.quaternion.premultiply(pitch).premultiply(yaw);
  state.dirty = true;
});

function toggleFrusta() {
  if (!state.frusta) return;
  state.frusta.visible = !state.frusta.visible;
  state.selected.visible = state.frusta.visible && state.snapped !== null;
  state.dirty = true;
  setStatus();
}

function togglePhoto() {
  if (!state.info.cameras.length) return;
  if (state.snapped === null) snapTo(nearestCamera(), true);
  else setPhoto(!state.showPhoto);
}

const actions = {
  o: () => setWalk(false), f: () => setWalk(!state.walk), c: toggleFrusta, l: () => setShaded(!state.shaded),
  n: () => state.info.cameras.length && snapTo(nearestCamera(), state.showPhoto), g: togglePhoto,
  '[': () => state.info.cameras.length && snapTo(trainIndex((state.snapped ?? 0) - 1), state.showPhoto),
  ']': () => state.info.cameras.length && snapTo(trainIndex((state.snapped ?? -1) + 1), state.showPhoto),
  escape: () => unsnap(), h: () => document.body.classList.toggle('clean'),
};
window.addEventListener('keydown', (e) => {
  const k = e.key.toLowerCase();
  if (e.shiftKey) state.keys.add('shift');
  if ('wasdqe'.includes(k) && k.length === 1) { state.keys.add(k); return; }
  if (actions[k] && state.info) actions[k]();
});
window.addEventListener('keyup', (e) => {
  state.keys.delete(e.key.toLowerCase());
  if (!e.shiftKey) state.keys.delete('shift');
});
window.addEventListener('blur', () => state.keys.clear());
window.addEventListener('resize', layout);
const buttons = {
  'btn-orbit': () => setWalk(false), 'btn-walk': () => setWalk(true), 'btn-frusta': toggleFrusta,
  'btn-shade': () => setShaded(!state.shaded), 'btn-nearest': actions.n, 'btn-photo': togglePhoto,
  'btn-prev': actions['['], 'btn-next': actions[']'],
};
for (const [id, fn] of Object.entries(buttons)) {
  document.getElementById(id).addEventListener('click', (e) => { e.target.blur(); if (state.info) fn(); });
}

// ---- loading ----------------------------------------------------------------------------------------------
async function fetchOk(url, kind) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return kind === 'json' ? r.json() : r.arrayBuffer();
}

function buildMesh(info, buf) {
  const V = info.num_vertices, F = info.num_faces;
  const posBytes = V * 12, colBytes = Math.ceil((V * 3) / 4) * 4;
  if (buf.byteLength !== posBytes + colBytes + F * 12) throw new Error(`mesh.bin has ${buf.byteLength} bytes, expected ${posBytes + colBytes + F * 12}`);
  const g = new BufferGeometry();
  g.setAttribute('position', new BufferAttribute(new Float32Array(buf, 0, V * 3), 3));
  const lut = new Float32Array(256).map((_, k) => { // sRGB bytes -> linear light (vertex colours are linear)
    const c = k / 255;
    return c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
  });
  const srgb = new Uint8Array(buf, posBytes, V * 3);
  g.setAttribute('color', new BufferAttribute(Float32Array.from(srgb, (c) => lut[c]), 3));
  g.setIndex(new BufferAttribute(new Uint32Array(buf, posBytes + colBytes, F * 3), 1));
  g.computeBoundingSphere();
  return new Mesh(g, new MeshBasicMaterial({ vertexColors: true, side: DoubleSide }));
}

async function loadGlb(info) {
  // the file as it is (GLTFLoader: KHR_materials_unlit -> MeshBasicMaterial, baseColorTexture sRGB, COLOR_0
  // linear, the sampler's filters and wraps), placed in the page's frame by glb_matrix (row-major)
  const buf = await fetchOk('/api/mesh.glb', 'bin');
  const gltf = await new GLTFLoader().parseAsync(buf, '');
  const group = new Group();
  group.matrixAutoUpdate = false;
  group.matrix.set(...info.glb_matrix);
  group.add(gltf.scene);
  group.updateMatrixWorld(true);
  return group;
}

function initialView() {
  const info = state.info;
  const lo = new Vector3(...info.bounds_min), hi = new Vector3(...info.bounds_max);
  const centre = lo.clone().add(hi).multiplyScalar(0.5);
  camera.up.copy(state.up);
  makeControls();
  controls.target.copy(centre);
  const fit = (OVERVIEW_FIT * state.radius) / Math.sin((camera.fov * Math.PI) / 360);
  if (info.cameras.length) { // from camera 0's side, framing the mesh: other cameras' frusta around it
    const c0 = new Vector3().setFromMatrixPosition(c2wMatrix(info.cameras[0]));
    const away = c0.sub(centre), dist = Math.max(fit, 1.25 * away.length());
    camera.position.copy(centre).addScaledVector(away.normalize(), dist);
  } else {
    const side = Math.abs(state.up.z) > 0.9 ? new Vector3(1, -1, 0) : new Vector3(1, 0, 1);
    const dir = side.normalize().multiplyScalar(0.88).addScaledVector(state.up, 0.47).normalize();
    camera.position.copy(centre).addScaledVector(dir, fit);
  }
  camera.lookAt(centre);
  controls.update();
}

function photoReady() {
  if (!state.showPhoto) return Promise.resolve(true);
  if (photo.complete && photo.naturalWidth > 0) return Promise.resolve(true);
  return new Promise((resolve) => {
    photo.addEventListener('load', () => resolve(true), { once: true });
    photo.addEventListener('error', () => { console.error(`cannot load ${photo.src}`); resolve(false); }, { once: true });
  });
}

async function main() {
  const info = await fetchOk('/api/scene.json', 'json');
  state.info = info;
  state.cams = [...info.cameras, ...(info.test_cameras || [])];
  document.getElementById('title').textContent = info.title;
  document.title = `${info.title} - trisplat viewer`;
  state.up.set(...info.up).normalize();
  const lo = new Vector3(...info.bounds_min), hi = new Vector3(...info.bounds_max);
  const centre = lo.clone().add(hi).multiplyScalar(0.5);
  state.radius = Math.max(hi.clone().sub(lo).length() / 2, 1e-6);
  const camDist = info.cameras.map((c) => new Vector3().setFromMatrixPosition(c2wMatrix(c)).distanceTo(centre)).sort((a, b) => a - b);
  state.extent = Math.max(state.radius, ...camDist);
  state.frustumDepth = FRUSTUM_SIZE * (camDist.length ? camDist[camDist.length >> 1] : state.radius);
  state.mesh = info.glb ? await loadGlb(info) : buildMesh(info, await fetchOk('/api/mesh.bin', 'bin'));
  scene.add(state.mesh);
  buildFrusta();
  initialView();
  layout();
  if (params.get('frusta') === '0') toggleFrusta();
  if (params.get('mode') === 'walk') setWalk(true);
  if (params.get('shaded') === '1') setShaded(true);
  if (params.has('cam') && info.cameras.length) snapTo(trainIndex(parseInt(params.get('cam'), 10) || 0), params.get('photo') === '1');
  if (params.has('testcam')) { // a held-out camera: ?testcam=K (0-based, in the capture's test split order)
    const k = parseInt(params.get('testcam'), 10);
    if (!(k >= 0 && k < (info.test_cameras || []).length)) throw new Error(`no test camera ${params.get('testcam')}`);
    snapTo(info.cameras.length + k, params.get('photo') === '1');
  }
  for (const key of (params.get('do') || '').split(',').filter(Boolean)) { // scripted key presses (tests, links)
    if (!actions[key]) throw new Error(`unknown action key in ?do=: ${key}`);
    actions[key]();
  }
  setStatus();
  requestAnimationFrame(frame);
  const photoOk = await photoReady();
  requestAnimationFrame(() => requestAnimationFrame(() => {
    const gl = renderer.getContext();
    window.trisplatReport({
      kind: 'ready', faces: info.num_faces, cameras: info.cameras.length, snapped: state.snapped, glb: info.glb,
      snapped_split: state.snapped === null ? null : state.cams[state.snapped].split,
      canvas: [renderer.domElement.width, renderer.domElement.height],
      photo: state.showPhoto && photoOk, webgl: gl.getParameter(gl.VERSION), drawn_triangles: renderer.info.render.triangles,
    });
    document.body.dataset.ready = '1';
  }));
}

main().catch((e) => { statusEl.textContent = `error: ${e.message}`; console.error(e.stack || String(e)); });
