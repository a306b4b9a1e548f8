// Camera paths: key frames recorded in the viewer, smoothed, written as nerfstudio's
// camera_path.json (what `ibr render --cameras` and `ns-render camera-path` read;
// ibr_pipeline/io/nerfstudio.py). Smoothing: Catmull-Rom splines through the key frames, on the
// optical centres and on the rotation quaternions (sign-aligned, renormalised), so the path passes
// through every key frame with a continuous velocity; the field of view is interpolated linearly.
import { RFromQuat, makeCamera, quatFromR } from "./camera.js";

// key frame of a camera: centre, rotation quaternion, vertical field of view (degrees), size
export function keyframe(cam) {
  return { center: [...cam.center], q: quatFromR(cam.R),
    fov: 2 * Math.atan(0.5 * cam.height / cam.K[1][1]) * 180 / Math.PI,
    width: cam.width, height: cam.height };
}

function catmullRom(p0, p1, p2, p3, t) {
  const t2 = t * t, t3 = t2 * t;
  return p1.map((_, i) => 0.5 * (2 * p1[i] + (-p0[i] + p2[i]) * t
    + (2 * p0[i] - 5 * p1[i] + 4 * p2[i] - p3[i]) * t2 + (-p0[i] + 3 * p1[i] - 3 * p2[i] + p3[i]) * t3));
}

// the camera of a key frame list at parameter u in [0, keys - 1]
function sample(keys, u) {
  const n = keys.length;
  const i = Math.min(Math.floor(u), n - 2), t = u - i;
  const at = (j) => keys[Math.max(0, Math.min(n - 1, j))];
  const [k0, k1, k2, k3] = [at(i - 1), at(i), at(i + 1), at(i + 2)];
  const center = catmullRom(k0.center, k1.center, k2.center, k3.center, t);
  let q = catmullRom(k0.q, k1.q, k2.q, k3.q, t);
  const nq = Math.hypot(...q);
  q = q.map((v) => v / nq);
  const fov = k1.fov + (k2.fov - k1.fov) * t;
  const { width: w, height: h } = keys[0];
  const f = 0.5 * h / Math.tan(fov * Math.PI / 360);
  const K = [[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]];  // the format's camera
  return makeCamera(K, RFromQuat(q), center, w, h);
}

// sign-align the quaternions (q and -q are one rotation) so the spline takes the short way
function aligned(keys) {
  const out = [];
  for (const k of keys) {
    let q = k.q;
    if (out.length) {
      const p = out[out.length - 1].q;
      if (p[0] * q[0] + p[1] * q[1] + p[2] * q[2] + p[3] * q[3] < 0) q = q.map((v) => -v);
    }
    out.push({ ...k, q });
  }
  return out;
}

// the smoothed cameras: `seconds` per key frame interval at `fps`, first and last key included
export function smoothPath(keys, seconds = 2, fps = 24) {
  if (keys.length < 2) throw new Error("a camera path needs at least 2 key frames");
  const k = aligned(keys);
  const frames = Math.max(2, Math.round((k.length - 1) * seconds * fps) + 1);
  const cams = [];
  for (let i = 0; i < frames; i++) cams.push(sample(k, (i / (frames - 1)) * (k.length - 1)));
  return cams;
}

// OpenCV world_from_cam x diag(1, -1, -1, 1): nerfstudio's OpenGL camera-to-world, row-major
export function c2wGL(cam) {
  const R = cam.R, c = cam.center;
  const M = [];
  for (let i = 0; i < 3; i++) M.push([R[0][i], -R[1][i], -R[2][i], c[i]]);
  M.push([0, 0, 0, 1]);
  return M.flat();
}

export function cameraPathJson(keys, seconds = 2, fps = 24) {
  const cams = smoothPath(keys, seconds, fps);
  const { width: w, height: h } = keys[0];
  const entry = (cam) => ({ camera_to_world: c2wGL(cam),
    fov: 2 * Math.atan(0.5 * h / cam.K[1][1]) * 180 / Math.PI, aspect: w / h });
  return { camera_type: "perspective", render_width: w, render_height: h, fps,
    seconds: cams.length / fps, smoothness_value: 0.5, is_cycle: false,
    keyframes: aligned(keys).map((k) => ({ center: k.center, quaternion_wxyz: k.q, fov: k.fov })),
    camera_path: cams.map(entry) };
}

export { sample as _sample };
