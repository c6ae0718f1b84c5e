// The page of `python -m splat_train view`: a trained model (3DGS PLY, or its .splat or .spz
// export: /state.json's "type", served at /model.<type>) rendered by Spark with the original
// 3DGS conventions (so a PLY matches `python -m splat_train render`), the COLMAP cameras as
// frusta, a seed toggle and a jump to any camera's pose and intrinsics.
// URL parameters: camera=NAME (start at that camera), seed=1 (show the seed), ui=0 (no panel,
// no frusta: a clean image of the model). window.viewerReady turns true once the view settled.
// Live: /state.json is polled every STATE_POLL_MS; when the server serves a new version of the
// model (a training run's snapshot replaced), it is loaded and swapped in, and the panel shows
// its training iteration (window.viewerIteration, window.viewerModelVersion).
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import { fixShPrecision } from "/shfix.js";

// Original 3DGS conventions (our rasterizer): a 0.3 px^2 screen-space dilation without opacity
// compensation, depth (not radial) order, a 3.33-sigma footprint, float colour per splat and
// float accumulation (8-bit blending drifts over many layers).
const SPARK_3DGS = {
  preBlurAmount: 0.3, blurAmount: 0.0, maxStdDev: 3.33, accumExtSplats: true,
  sortRadial: false, clipXY: 1.4, minAlpha: 1.0 / 255.0, premultipliedAlpha: true,
};
const NEAR = 0.01, FAR = 1000.0;
// A .spz stores the right-up-back (OpenGL) frame: the PLY's right-down-front (OpenCV) world
// turned 180 degrees about x (camio.splatfmt.rdf_to_rub). Spark 2.2.0 reads a .spz's positions,
// rotations and SH bands as stored and converts no frame, so the mesh is turned back by the
// same half turn about x (quaternion x=1, w=0) to line up with the cameras, which are in the
// PLY's frame (measured on tests/test_view_browser.py's scene, SH degree 0: 52 dB against the
// PLY's image turned, 12 dB not).
// A .splat is written in the PLY's frame and needs no turn.
const SPZ_TO_PLY_FRAME = new THREE.Quaternion(1, 0, 0, 0);
const STATE_POLL_MS = 1000;
const params = new URLSearchParams(window.location.search);
const showUi = params.get("ui") !== "0";
const statusEl = document.getElementById("status");
const iterationEl = document.getElementById("iteration");
if (!showUi) document.getElementById("panel").classList.add("hidden");
window.viewerReady = false;
window.viewerError = null;
window.viewerIteration = null;
window.viewerModelVersion = 0;
const status = (msg) => { statusEl.textContent = msg; };

const canvas = document.getElementById("view");
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, alpha: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.outputColorSpace = THREE.LinearSRGBColorSpace;  // the PLY's colours are written as they are
renderer.setClearColor(0x000000, 1);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(50, 1, NEAR, FAR);
let lastDirty = performance.now();
const spark = new SparkRenderer({ renderer, ...SPARK_3DGS, onDirty: () => { lastDirty = performance.now(); } });
// Blend the PLY's values as they are (3DGS does not linearise): never convert sRGB to linear.
Object.defineProperty(spark.uniforms.encodeLinear, "value", { get: () => false, set: () => {} });
scene.add(spark);
let controls = null;
function makeControls(target) {
  // OrbitControls keeps camera.up fixed: set it to the camera's own up so a jump keeps its roll
  if (controls) controls.dispose();
  controls = new OrbitControls(camera, canvas);
  controls.target.copy(target);
  controls.update();
  controls.addEventListener("start", () => { activeCam = null; cameraSelect.value = ""; layout(); });
}

// Float target: splats accumulate in half floats, then one copy to the 8-bit canvas.
let target = new THREE.WebGLRenderTarget(1, 1, { type: THREE.HalfFloatType, depthBuffer: true });
const blitScene = new THREE.Scene();
const blitCam = new THREE.OrthographicCamera(-1, 1, 1, -1, 0, 1);
const blitMat = new THREE.ShaderMaterial({
  uniforms: { src: { value: null } },
  vertexShader: "varying vec2 vUv; void main() { vUv = uv; gl_Position = vec4(position.xy, 0.0, 1.0); }",
  fragmentShader: "uniform sampler2D src; varying vec2 vUv; void main() { vec4 c = texture2D(src, vUv); gl_FragColor = vec4(clamp(c.rgb, 0.0, 1.0), 1.0); }",
  depthTest: false, depthWrite: false,
});
blitScene.add(new THREE.Mesh(new THREE.PlaneGeometry(2, 2), blitMat));

let cameras = [];
let activeCam = null;   // the record whose intrinsics drive the projection, or null
let model = null, seed = null;
const frusta = new THREE.Group();
scene.add(frusta);
frusta.visible = showUi;

function worldFromCamGl(rec) {
  // OpenCV cam_from_world [R|t] -> three.js camera matrix (x right, y up, looking down -z)
  const R = rec.cam_from_world, m = new THREE.Matrix4();
  m.set(R[0][0], R[0][1], R[0][2], R[0][3], R[1][0], R[1][1], R[1][2], R[1][3],
        R[2][0], R[2][1], R[2][2], R[2][3], 0, 0, 0, 1);
  m.invert();
  return m.multiply(new THREE.Matrix4().makeScale(1, -1, -1));
}

function projectionFromK(rec) {
  // COLMAP pixels (top-left pixel centre at 0.5): the principal point moves the image centre
  const [fx, cx] = [rec.K[0][0], rec.K[0][2]], [fy, cy] = [rec.K[1][1], rec.K[1][2]];
  const W = rec.width, H = rec.height, n = NEAR, f = FAR;
  const P = new THREE.Matrix4();
  P.set(2 * fx / W, 0, 1 - 2 * cx / W, 0,
        0, 2 * fy / H, 2 * cy / H - 1, 0,
        0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
        0, 0, -1, 0);
  return P;
}

function layout() {
  // the canvas keeps the active camera's aspect (letterboxed); otherwise it fills the window
  let w = window.innerWidth, h = window.innerHeight;
  if (activeCam) {
    const s = Math.min(w / activeCam.width, h / activeCam.height);
    w = Math.max(1, Math.round(activeCam.width * s)); h = Math.max(1, Math.round(activeCam.height * s));
  }
  renderer.setSize(w, h, true);
  canvas.style.left = `${Math.floor((window.innerWidth - w) / 2)}px`;
  canvas.style.top = `${Math.floor((window.innerHeight - h) / 2)}px`;
  if (target.width !== w || target.height !== h) target.setSize(w, h);
  if (activeCam) {
    camera.projectionMatrix.copy(projectionFromK(activeCam));
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  } else {
    camera.aspect = w / h; camera.updateProjectionMatrix();
  }
}

function jumpTo(rec) {
  activeCam = rec;
  const m = worldFromCamGl(rec), pos = new THREE.Vector3(), q = new THREE.Quaternion(), s = new THREE.Vector3();
  m.decompose(pos, q, s);
  camera.position.copy(pos); camera.quaternion.copy(q); camera.updateMatrixWorld(true);
  // orbit about a point ahead of the camera, at the distance of the scene's middle
  camera.up.set(0, 1, 0).applyQuaternion(q);
  makeControls(new THREE.Vector3(0, 0, -sceneScale).applyQuaternion(q).add(pos));
  camera.quaternion.copy(q); camera.updateMatrixWorld(true);
  layout();
}

let sceneScale = 1.0;
function addFrusta() {
  const centers = cameras.map((r) => new THREE.Vector3().setFromMatrixPosition(worldFromCamGl(r)));
  const mid = centers.reduce((a, c) => a.add(c), new THREE.Vector3()).multiplyScalar(1 / Math.max(1, centers.length));
  const spread = centers.length > 1 ? Math.max(...centers.map((c) => c.distanceTo(mid))) : 1.0;
  sceneScale = Math.max(spread * 2, 1e-3);
  const d = Math.max(spread * 0.25, 1e-3);
  for (const r of cameras) {
    const [fx, cx, fy, cy] = [r.K[0][0], r.K[0][2], r.K[1][1], r.K[1][2]];
    const corners = [[0, 0], [r.width, 0], [r.width, r.height], [0, r.height]].map(([u, v]) =>
      new THREE.Vector3((u - cx) / fx * d, -(v - cy) / fy * d, -d));
    const o = new THREE.Vector3();
    const pts = [];
    for (let i = 0; i < 4; i++) pts.push(o, corners[i], corners[i], corners[(i + 1) % 4]);
    const geo = new THREE.BufferGeometry().setFromPoints(pts);
    const lines = new THREE.LineSegments(geo, new THREE.LineBasicMaterial({ color: r.role === "test" ? 0xff9933 : 0x33ff66 }));
    lines.matrixAutoUpdate = false;
    lines.matrix.copy(worldFromCamGl(r));
    frusta.add(lines);
  }
}

const cameraSelect = document.getElementById("camera");
cameraSelect.addEventListener("change", () => {
  const rec = cameras.find((r) => r.name === cameraSelect.value);
  if (rec) jumpTo(rec); else { activeCam = null; layout(); }
});
document.getElementById("frusta").addEventListener("change", (e) => { frusta.visible = e.target.checked; });
document.getElementById("seed").addEventListener("change", (e) => showSeed(e.target.checked));
window.addEventListener("resize", layout);

async function loadSplats(url, bytes = null, fileType = "ply") {
  // extSplats: float colour per splat, so base colours above 1 are not clamped before SH is added
  if (bytes === null) bytes = new Uint8Array(await (await fetch(url)).arrayBuffer());
  const mesh = new SplatMesh({ fileBytes: bytes.slice(), fileType, extSplats: true });
  await mesh.initialized;
  if (fileType === "spz") mesh.quaternion.copy(SPZ_TO_PLY_FRAME);
  let fix = `not a PLY (${fileType}): as Spark reads it`;
  if (fileType === "ply") {  // the SH re-encoding reads the PLY's own floats
    try { fix = fixShPrecision(mesh.extSplats ?? mesh.splats, bytes); } catch (e) { fix = `failed: ${e}`; }
    if (fix !== "applied") console.warn(`SH bands of ${url} at Spark's precision: ${fix}`);
  }
  window.viewerShFix = Object.assign(window.viewerShFix || {}, { [url]: fix });
  return mesh;
}

async function showSeed(on) {
  if (on && !seed) { status("loading the seed..."); seed = await loadSplats("/seed.ply"); scene.add(seed); }
  if (seed) seed.visible = on;
  if (model) model.visible = !on;
  lastDirty = performance.now();
  status(on ? "showing the seed" : "showing the trained model");
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

let modelType = "ply";  // /state.json's "type": Spark's fileType, the suffix of the model's URL
async function fetchModel() {
  // the served model's bytes and the version and iteration they belong to (one response);
  // null while the server has none yet (503: a training run before its first snapshot)
  const url = `/model.${modelType}`;
  const resp = await fetch(url, { cache: "no-store" });
  if (resp.status === 503) return null;
  if (!resp.ok) throw new Error(`${url}: HTTP ${resp.status}`);
  const version = Number(resp.headers.get("X-Model-Version") || 0);
  const it = resp.headers.get("X-Model-Iteration");
  const bytes = new Uint8Array(await resp.arrayBuffer());
  return { version, iteration: it ? Number(it) : null, mesh: await loadSplats(url, bytes, modelType) };
}

function showIteration(it) {
  window.viewerIteration = it;
  iterationEl.textContent = it === null ? "" : `iteration ${it}`;
  iterationEl.classList.toggle("hidden", it === null);
}

function swapModel(next) {
  const seedShown = document.getElementById("seed").checked;
  if (model) { scene.remove(model); if (model.dispose) model.dispose(); }
  model = next.mesh;
  model.visible = !seedShown;
  scene.add(model);
  window.viewerModelVersion = next.version;
  showIteration(next.iteration);
  lastDirty = performance.now();
}

async function followModel() {
  // poll the served version; load and swap a newer model (never two loads at once)
  while (true) {
    await sleep(STATE_POLL_MS);
    try {
      const state = await (await fetch("/state.json", { cache: "no-store" })).json();
      if (state.version && state.version !== window.viewerModelVersion) {
        const next = await fetchModel();
        if (next && next.version !== window.viewerModelVersion) {
          swapModel(next);
          if (window.viewerReady) status(`ready: ${model.numSplats ?? ""} Gaussians`);
        }
      }
    } catch (e) { console.warn(`following the model: ${e}`); }
  }
}

let frames = 0, loadedAt = null;
function frame() {
  if (controls && !activeCam) controls.update();
  renderer.setRenderTarget(target);
  renderer.clear();
  renderer.render(scene, camera);
  renderer.setRenderTarget(null);
  blitMat.uniforms.src.value = target.texture;
  renderer.render(blitScene, blitCam);
  frames += 1;
  const now = performance.now();
  if (loadedAt !== null && !window.viewerReady && now - lastDirty > 300 && now - loadedAt > 500 && frames > 10) {
    window.viewerReady = true;
    status(`ready: ${model.numSplats ?? ""} Gaussians`);
  }
}

async function main() {
  const [camsResp, viewResp, stateResp] = await Promise.all(
    [fetch("/cameras.json"), fetch("/view.json"), fetch("/state.json", { cache: "no-store" })]);
  cameras = (await camsResp.json()).cameras;
  const view = await viewResp.json();
  modelType = (await stateResp.json()).type;
  window.viewerModelType = modelType;
  // the colour the model was trained against, as the trainer composites it (no sRGB conversion)
  const bg = view.background;
  renderer.setClearColor(new THREE.Color().setRGB(bg[0], bg[1], bg[2], THREE.LinearSRGBColorSpace), 1);
  if (view.seed) document.getElementById("seedrow").classList.remove("hidden");
  for (const r of cameras) {
    const opt = document.createElement("option");
    opt.value = r.name; opt.textContent = `${r.role === "test" ? "held-out" : "training"}: ${r.name}`;
    cameraSelect.appendChild(opt);
  }
  addFrusta();
  const want = params.get("camera");
  const start = cameras.find((r) => r.name === want) || null;
  if (want && !start) throw new Error(`no camera named ${want}`);
  if (start) { cameraSelect.value = start.name; jumpTo(start); }
  else if (cameras.length) { jumpTo(cameras[0]); activeCam = null; cameraSelect.value = ""; layout(); }
  else { camera.position.set(0, 0, 3); makeControls(new THREE.Vector3()); layout(); }
  renderer.setAnimationLoop(frame);
  let first = await fetchModel();
  while (first === null) {
    status("waiting for the training run's first snapshot...");
    await sleep(STATE_POLL_MS);
    first = await fetchModel();
  }
  swapModel(first);
  followModel();
  if (params.get("seed") === "1" && view.seed) { document.getElementById("seed").checked = true; await showSeed(true); }
  lastDirty = performance.now();
  loadedAt = performance.now();
  window.viewerLoadMs = loadedAt;
  status("rendering...");
}

main().catch((e) => { window.viewerError = String(e && e.stack || e); status(`error: ${e}`); console.error(e); });
