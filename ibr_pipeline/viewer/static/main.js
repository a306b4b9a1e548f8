// The viewer page: loads the bundle (data/manifest.json), renders with IBRRenderer on demand,
// navigation (orbit / walk: mouse, keyboard, touch), frusta, layer modes, key frames -> camera
// paths, and `window.ibr`, the API the browser test drives.
import { add, cross, fromManifest, glMat, lookRotation, makeCamera, norm, projection, scale, sub,
  unit } from "./camera.js";
import { cameraPathJson, keyframe, smoothPath } from "./path.js";
import { LINES_FS, LINES_VS } from "./post.js";
import { IBRRenderer } from "./renderer.js";

const params = new URLSearchParams(location.search);
const canvas = document.getElementById("view");
const hud = (id) => document.getElementById(id);
const state = { mode: params.get("mode") || "composite", nav: "walk", frusta: params.get("frusta") !== "0",
  keys: [], dirty: true, prev: null, times: [], held: new Set(), last: null };

function fail(msg) {
  hud("status").textContent = msg;
  hud("status").classList.add("error");
  window.ibr = { error: msg };
  throw new Error(msg);
}

const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true,
  premultipliedAlpha: false });
if (!gl) fail("This browser has no WebGL2: use a current Chrome, Firefox or Safari.");

const t0 = performance.now();
const manifest = await fetch("data/manifest.json").then((r) => {
  if (!r.ok) fail(`data/manifest.json: HTTP ${r.status}: run \`ibr view WS\` to write and serve the bundle`);
  return r.json();
});
let R;
try { R = new IBRRenderer(gl, manifest, "data/"); } catch (e) { fail(String(e.message || e)); }
const views = R.views.map((v) => v.cam);
const heldout = (manifest.heldout || []).map(fromManifest);
const fly = (manifest.fly || []).map(fromManifest);

// scene scale and "up" from the capture: cameras' image y axis points down
const up = unit(views.reduce((a, v) => sub(a, v.R[1]), [0, 0, 0]));
const lo = [0, 1, 2].map((i) => Math.min(...views.map((v) => v.center[i])));
const hi = [0, 1, 2].map((i) => Math.max(...views.map((v) => v.center[i])));
const extent = Math.max(norm(sub(hi, lo)), 0.1);
const ref = (() => {  // horizontal reference direction for yaw
  const a = views[0].axis;
  const h = sub(a, scale(up, a[0] * up[0] + a[1] * up[1] + a[2] * up[2]));
  return norm(h) > 1e-6 ? unit(h) : unit(cross(up, [1, 0, 0]));
})();
const ref2 = cross(up, ref);

// the navigation camera: centre + yaw/pitch about `up`, the first view's intrinsics made centred
// (what camera_path.json can store); jumping to a capture / held-out camera uses it exactly
const base = views[0];
const f0 = base.K[1][1];
const navK = [[f0, 0, (base.width - 1) / 2], [0, f0, (base.height - 1) / 2], [0, 0, 1]];
const nav = { center: [...base.center], yaw: 0, pitch: 0, radius: extent * 0.5, exact: null };

function setFromCamera(cam) {
  const a = cam.axis;
  nav.center = [...cam.center];
  nav.yaw = Math.atan2(a[0] * ref2[0] + a[1] * ref2[1] + a[2] * ref2[2], a[0] * ref[0] + a[1] * ref[1] + a[2] * ref[2]);
  nav.pitch = Math.asin(Math.max(-1, Math.min(1, a[0] * up[0] + a[1] * up[1] + a[2] * up[2])));
  nav.exact = cam;
  state.dirty = true;
}
function forward() {
  const c = Math.cos(nav.pitch);
  return add(scale(add(scale(ref, Math.cos(nav.yaw)), scale(ref2, Math.sin(nav.yaw))), c), scale(up, Math.sin(nav.pitch)));
}
function navCamera() {
  return makeCamera(navK, lookRotation(forward(), up), nav.center, base.width, base.height);
}
function currentCamera() { return nav.exact || navCamera(); }
function moved() { nav.exact = null; state.dirty = true; }

// --- frusta and the key-frame path as lines ----------------------------------------------------
const lines = { prog: null, vao: gl.createVertexArray(), buf: gl.createBuffer(), count: 0 };
{
  const mk = (type, src) => { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s); return s; };
  lines.prog = gl.createProgram();
  gl.attachShader(lines.prog, mk(gl.VERTEX_SHADER, LINES_VS));
  gl.attachShader(lines.prog, mk(gl.FRAGMENT_SHADER, LINES_FS));
  gl.bindAttribLocation(lines.prog, 0, "in_pos");
  gl.bindAttribLocation(lines.prog, 1, "in_color");
  gl.linkProgram(lines.prog);
}
function frustum(cam, color, size, out) {
  const K = cam.K, w = cam.width, h = cam.height;
  const ray = (u, v) => {  // world point at depth `size` through pixel (u, v)
    const x = (u - K[0][2]) / K[0][0] * size, y = (v - K[1][2]) / K[1][1] * size;
    return add(cam.center, add(add(scale(cam.R[0], x), scale(cam.R[1], y)), scale(cam.R[2], size)));
  };
  const c = [ray(0, 0), ray(w - 1, 0), ray(w - 1, h - 1), ray(0, h - 1)];
  for (let i = 0; i < 4; i++) out.push(...cam.center, ...color, ...c[i], ...color, ...c[i], ...color, ...c[(i + 1) % 4], ...color);
}
function drawLines(cam, selected) {
  const data = [];
  const size = extent * 0.04;
  const sel = new Set(selected);
  if (state.frusta) {
    views.forEach((v, k) => frustum(v, sel.has(k) ? [1, 0.55, 0] : [0.6, 0.6, 0.6], size, data));
    heldout.forEach((v) => frustum(v, [0, 0.8, 1], size, data));
  }
  if (state.keys.length >= 2) {
    const cams = smoothPath(state.keys, 1, 12);
    for (let i = 1; i < cams.length; i++) data.push(...cams[i - 1].center, 0.2, 1, 0.2, ...cams[i].center, 0.2, 1, 0.2);
  }
  if (!data.length) return;
  gl.bindVertexArray(lines.vao);
  gl.bindBuffer(gl.ARRAY_BUFFER, lines.buf);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data), gl.DYNAMIC_DRAW);
  gl.enableVertexAttribArray(0);
  gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 24, 0);
  gl.enableVertexAttribArray(1);
  gl.vertexAttribPointer(1, 3, gl.FLOAT, false, 24, 12);
  gl.useProgram(lines.prog);
  gl.uniformMatrix4fv(gl.getUniformLocation(lines.prog, "P_n"), false, glMat(projection(cam, manifest.near, manifest.far)));
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.drawArrays(gl.LINES, 0, data.length / 6);
  gl.bindVertexArray(null);
}

// --- frames ---------------------------------------------------------------------------------------
function sizeCanvas(cam) {
  if (canvas.width !== cam.width || canvas.height !== cam.height) {
    canvas.width = cam.width; canvas.height = cam.height;
  }
}
function frame(cam, opts = {}) {
  sizeCanvas(cam);
  const r = R.render(cam, opts.mode || state.mode, opts.previous === undefined ? state.prev : opts.previous);
  state.prev = { R: cam.R, center: cam.center, selected: r.selected };
  if (opts.overlay !== false) drawLines(cam, r.selected);
  state.times.push(r.ms);
  if (state.times.length > 60) state.times.shift();
  const med = [...state.times].sort((a, b) => a - b)[state.times.length >> 1];
  hud("ms").textContent = `${r.ms.toFixed(1)} ms (median of last ${state.times.length}: ${med.toFixed(1)} ms)`;
  hud("sel").textContent = r.selected.map((k) => views[k].name).join(", ") + (r.missing ? ` (${r.missing} loading)` : "");
  hud("mem").textContent = `${R.gpu.size} layers resident, ${(R.bytes / 2 ** 20).toFixed(0)} MB`;
  return r;
}

// one frame of `cam` once its views are loaded; opts.sequence: hysteresis from the last frame
// (a camera path), else none (an unrelated view, as `ibr render --cameras cameras.json`)
async function renderCamera(cam, opts = {}) {
  const mode = opts.mode || state.mode;
  const previous = opts.sequence ? state.prev : null;
  await R.ensure(R.renderSelection(cam, mode, previous), mode);
  return frame(cam, { overlay: false, previous, mode });
}

// prefetch every view's layers, nearest first, a few at a time
async function prefetch() {
  const c = currentCamera();
  const order = views.map((v, k) => [norm(sub(v.center, c.center)), k]).sort((a, b) => a[0] - b[0]).map((x) => x[1]);
  const queue = [...order];
  const worker = async () => { while (queue.length) { await R.ensure([queue.shift()], state.mode); state.dirty = true; } };
  await Promise.all([worker(), worker(), worker(), worker()]);
}

// --- input ---------------------------------------------------------------------------------------
const speed = () => extent * 0.3;
function look(dx, dy) {
  if (state.nav === "orbit") {
    const target = add(nav.center, scale(forward(), nav.radius));
    nav.yaw -= dx * 0.005; nav.pitch = Math.max(-1.5, Math.min(1.5, nav.pitch + dy * 0.005));
    nav.center = sub(target, scale(forward(), nav.radius));
  } else {
    nav.yaw -= dx * 0.003; nav.pitch = Math.max(-1.5, Math.min(1.5, nav.pitch + dy * 0.003));
  }
  moved();
}
function dolly(amount) {
  if (state.nav === "orbit") {
    const target = add(nav.center, scale(forward(), nav.radius));
    nav.radius = Math.max(extent * 0.02, nav.radius * Math.exp(amount));
    nav.center = sub(target, scale(forward(), nav.radius));
  } else {
    nav.center = add(nav.center, scale(forward(), -amount * extent * 0.2));
  }
  moved();
}
function pan(dx, dy) {
  const cam = currentCamera();
  nav.center = add(nav.center, add(scale(cam.R[0], -dx * extent * 0.002), scale(cam.R[1], -dy * extent * 0.002)));
  moved();
}
let drag = null;
canvas.addEventListener("pointerdown", (e) => { drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey }; canvas.setPointerCapture(e.pointerId); });
canvas.addEventListener("pointermove", (e) => {
  if (!drag || e.pointerType === "touch") return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  drag.x = e.clientX; drag.y = e.clientY;
  if (drag.pan) pan(dx, dy); else look(dx, dy);
});
canvas.addEventListener("pointerup", () => { drag = null; });
canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("wheel", (e) => { e.preventDefault(); dolly(Math.sign(e.deltaY) * 0.1); }, { passive: false });
let touch = null;  // one finger: look / orbit; two: pinch = dolly, drag = pan
const touchInfo = (ts) => {
  const p = [...ts].map((t) => [t.clientX, t.clientY]);
  const c = p.reduce((a, q) => [a[0] + q[0] / p.length, a[1] + q[1] / p.length], [0, 0]);
  return { n: p.length, c, d: p.length > 1 ? Math.hypot(p[0][0] - p[1][0], p[0][1] - p[1][1]) : 0 };
};
canvas.addEventListener("touchstart", (e) => { e.preventDefault(); touch = touchInfo(e.touches); }, { passive: false });
canvas.addEventListener("touchmove", (e) => {
  e.preventDefault();
  const t = touchInfo(e.touches);
  if (touch && t.n === touch.n) {
    if (t.n === 1) look(t.c[0] - touch.c[0], t.c[1] - touch.c[1]);
    else { pan(t.c[0] - touch.c[0], t.c[1] - touch.c[1]); if (touch.d > 0 && t.d > 0) dolly(-Math.log(t.d / touch.d)); }
  }
  touch = t;
}, { passive: false });
canvas.addEventListener("touchend", (e) => { touch = touchInfo(e.touches); });

let viewIndex = 0, heldIndex = -1;
const actions = {
  n: () => { viewIndex = (viewIndex + 1) % views.length; setFromCamera(views[viewIndex]); },
  b: () => { viewIndex = (viewIndex + views.length - 1) % views.length; setFromCamera(views[viewIndex]); },
  h: () => { if (heldout.length) { heldIndex = (heldIndex + 1) % heldout.length; setFromCamera(heldout[heldIndex]); } },
  1: () => setMode("composite"), 2: () => setMode("surface"), 3: () => setMode("reflection"), 4: () => setMode("single"),
  f: () => { state.frusta = !state.frusta; state.dirty = true; },
  m: () => { state.nav = state.nav === "walk" ? "orbit" : "walk"; hud("nav").textContent = state.nav; },
  k: () => addKeyframe(),
  p: () => play(state.keys.length >= 2 ? smoothPath(state.keys) : fly),
  c: () => { state.keys = []; hud("keys").textContent = "0"; state.dirty = true; },
  x: () => savePath(),
};
const MOVE = { w: [1, 0, 0], s: [-1, 0, 0], a: [0, -1, 0], d: [0, 1, 0], e: [0, 0, 1], q: [0, 0, -1] };
window.addEventListener("keydown", (e) => {
  const k = e.key.toLowerCase();
  if (MOVE[k]) { state.held.add(k); e.preventDefault(); } else if (actions[k] && !e.repeat) { actions[k](); e.preventDefault(); }
});
window.addEventListener("keyup", (e) => state.held.delete(e.key.toLowerCase()));
document.querySelectorAll("[data-key]").forEach((b) => b.addEventListener("click", () => actions[b.dataset.key]()));

function setMode(m) { state.mode = m; hud("mode").value = m; state.dirty = true; }
hud("mode").addEventListener("change", (e) => setMode(e.target.value));
function addKeyframe() { state.keys.push(keyframe(currentCamera())); hud("keys").textContent = String(state.keys.length); state.dirty = true; }
function savePath() {
  if (state.keys.length < 2) { hud("status").textContent = "record at least 2 key frames (K) first"; return; }
  const blob = new Blob([JSON.stringify(cameraPathJson(state.keys), null, 1)], { type: "application/json" });
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob); a.download = "camera_path.json"; a.click();
  hud("status").textContent = "saved camera_path.json: render it with `ibr render WS --cameras camera_path.json`";
}
async function play(cams) {
  if (!cams.length) return;
  for (const c of cams) { await R.ensure(R.renderSelection(c, state.mode, state.prev), state.mode); frame(c); await new Promise(requestAnimationFrame); }
  setFromCamera(cams[cams.length - 1]);
}

function tick(now) {
  const dt = state.last ? Math.min((now - state.last) / 1000, 0.1) : 0;
  state.last = now;
  if (state.held.size) {
    const cam = currentCamera();
    let m = [0, 0, 0];
    for (const k of state.held) m = add(m, MOVE[k]);
    const fwd = forward();
    nav.center = add(nav.center, scale(add(add(scale(fwd, m[0]), scale(cam.R[0], m[1])), scale(up, m[2])), speed() * dt));
    moved();
  }
  if (state.dirty) {
    state.dirty = false;
    const cam = currentCamera();
    const r = frame(cam);
    if (r.missing) R.ensure(r.selected, state.mode).then(() => { state.dirty = true; });
  }
  requestAnimationFrame(tick);
}

// --- start ----------------------------------------------------------------------------------------
const startName = params.get("view");
const start = startName ? views.find((v) => v.name === startName) || heldout.find((v) => v.name === startName) : views[0];
if (!start) fail(`?view=${startName}: no such camera in the bundle`);
setFromCamera(start);
await R.ensure(R.renderSelection(start, state.mode, null), state.mode);
const first = frame(start, { previous: null });
const loadMs = performance.now() - t0;
hud("status").textContent = `${manifest.workspace}: ${views.length} views, first frame after ${(loadMs / 1000).toFixed(2)} s`;
hud("nav").textContent = state.nav;
hud("mode").value = state.mode;
const prefetched = params.get("prefetch") === "0" ? Promise.resolve() : prefetch().then(() => {
  hud("status").textContent += `, all views loaded after ${((performance.now() - t0) / 1000).toFixed(2)} s`;
  return performance.now() - t0;
});
requestAnimationFrame(tick);

window.ibr = {
  manifest, loadMs, firstFrame: first, prefetched,
  names: views.map((v) => v.name),
  renderCamera: async (c, opts = {}) => {
    const cam = c.cam_from_world ? fromManifest(c) : c;
    const r = await renderCamera(cam, opts);
    state.dirty = false;
    return { ms: r.ms, select_ms: r.select_ms, gl_ms: r.gl_ms, phases: r.phases, selected: r.selected.map((k) => views[k].name), weights: r.weights };
  },
  select: (c, previous = null) => R.renderSelection(c.cam_from_world ? fromManifest(c) : c, "composite", previous).map((k) => views[k].name),
  goTo: (name) => setFromCamera(views.find((v) => v.name === name) || heldout.find((v) => v.name === name)),
  camera: () => currentCamera(),
  navCamera: () => navCamera(),
  keys: () => state.keys,
  cameraPath: (seconds = 2, fps = 24) => cameraPathJson(state.keys, seconds, fps),
  profile: (on) => { R.profile = on; },
  stats: () => ({ resident: R.gpu.size, bytes: R.bytes, times: [...state.times] }),
};
