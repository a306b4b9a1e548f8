// Cameras and matrices of the viewer, in the conventions of ibr_pipeline/scene.py and
// render/gl.py: OpenCV axes (x right, y down, z forward), cam_from_world = [R | t], intrinsics K
// with the top-left pixel centre at (0, 0), image row v drawn at GL row v. A dozen 4x4 and 3x3
// helpers are written out here rather than taken from a matrix library: the viewer has no
// JavaScript dependencies to install, pin or vendor.
import { dot, norm, sub } from "./selection.js";

export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
  a[0] * b[1] - a[1] * b[0]];
export const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
export const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const unit = (a) => scale(a, 1 / Math.max(norm(a), 1e-12));

// a camera from K, R (rows), centre and size; t = -R c
export function makeCamera(K, R, center, width, height) {
  const t = [-dot(R[0], center), -dot(R[1], center), -dot(R[2], center)];
  return { K, R, t, center: [...center], axis: [...R[2]], width, height };
}

// a camera of the bundle (manifest.json entry)
export function fromManifest(c) {
  const R = c.cam_from_world.map((row) => row.slice(0, 3));
  const t = c.cam_from_world.map((row) => row[3]);
  const center = [0, 1, 2].map((j) => -(R[0][j] * t[0] + R[1][j] * t[1] + R[2][j] * t[2]));
  return { name: c.name, K: c.K, R, t, center, axis: [...R[2]], width: c.width, height: c.height };
}

// rows of a rotation looking along `forward` with image "up" towards `up` (OpenCV axes)
export function lookRotation(forward, up) {
  const z = unit(forward);
  let x = cross(z, up);                      // y points down: x = y x z = z x up
  if (norm(x) < 1e-9) x = cross(z, [1, 0, 0]);
  x = unit(x);
  const y = cross(z, x);
  return [x, y, z];
}

// 4x4 row-major products and GL uploads (column-major Float32Array)
export function mat4mul(A, B) {
  const C = [];
  for (let i = 0; i < 4; i++) {
    C.push([0, 1, 2, 3].map((j) => A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j]
      + A[i][3] * B[3][j]));
  }
  return C;
}
export function glMat(M) {
  const out = new Float32Array(16);
  for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) out[j * 4 + i] = M[i][j];
  return out;
}
export function camFromWorld4(cam) {
  return [[...cam.R[0], cam.t[0]], [...cam.R[1], cam.t[1]], [...cam.R[2], cam.t[2]], [0, 0, 0, 1]];
}

// gl.projection: OpenCV intrinsics -> clip space, pixel-centre convention, no row flip
export function projection(cam, near, far) {
  const K = cam.K, W = cam.width, H = cam.height;
  const P = [[2 * K[0][0] / W, 2 * K[0][1] / W, (2 * K[0][2] + 1) / W - 1, 0],
    [0, 2 * K[1][1] / H, (2 * K[1][2] + 1) / H - 1, 0],
    [0, 0, (far + near) / (far - near), -2 * far * near / (far - near)],
    [0, 0, 1, 0]];
  return mat4mul(P, camFromWorld4(cam));
}

// gl.source_matrix: world -> (u z, v z, z, 1)
export function sourceMatrix(cam) {
  const V = camFromWorld4(cam);
  const K = cam.K;
  const S = [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]];
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 4; j++) S[i][j] = K[i][0] * V[0][j] + K[i][1] * V[1][j] + K[i][2] * V[2][j];
  }
  return S;
}

// --- rotations as quaternions (w, x, y, z), for smoothing key frames ---------------------------
export function quatFromR(R) {
  const [m00, m01, m02] = R[0], [m10, m11, m12] = R[1], [m20, m21, m22] = R[2];
  const tr = m00 + m11 + m22;
  let q;
  if (tr > 0) {
    const s = Math.sqrt(tr + 1) * 2;
    q = [0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s];
  } else if (m00 > m11 && m00 > m22) {
    const s = Math.sqrt(1 + m00 - m11 - m22) * 2;
    q = [(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s];
  } else if (m11 > m22) {
    const s = Math.sqrt(1 + m11 - m00 - m22) * 2;
    q = [(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s];
  } else {
    const s = Math.sqrt(1 + m22 - m00 - m11) * 2;
    q = [(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s];
  }
  const n = Math.hypot(...q);
  return q.map((v) => v / n);
}
export function RFromQuat(q) {
  const [w, x, y, z] = q;
  return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
}
export function slerp(a, b, t) {
  let d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
  const bb = d < 0 ? b.map((v) => -v) : b;
  d = Math.abs(d);
  if (d > 0.9995) {
    const q = a.map((v, i) => v + t * (bb[i] - v));
    const n = Math.hypot(...q);
    return q.map((v) => v / n);
  }
  const th = Math.acos(d), s = Math.sin(th);
  const wa = Math.sin((1 - t) * th) / s, wb = Math.sin(t * th) / s;
  return a.map((v, i) => wa * v + wb * bb[i]);
}

export { dot, norm, sub };
