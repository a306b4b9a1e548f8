// View distance (Eq. 14) and view selection (§5.1.2, Fig. 7) of Xu et al. 2021: a line-by-line
// port of ibr_pipeline/render/selection.py and blend.view_weights, in doubles as numpy computes
// them, so that the browser selects the same views with the same weights as `ibr render` (the
// browser test compares the two). Cameras: {R: 3x3 rows (cam_from_world), center, axis}.

export const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => { const n = Math.max(norm(a), 1e-12); return [a[0] / n, a[1] / n, a[2] / n]; };

// angle in degrees between two axes
export function axisAngleDeg(a, b) {
  const c = Math.min(1, Math.max(-1, dot(unit(a), unit(b))));
  return Math.acos(c) * 180 / Math.PI;
}

// Eq. 14 as selection.view_distance: d_k = angle(R_k^z, R_n^z) [rad] + lambda |t_k - t_n| / D,
// D the scene's median depth
export function viewDistance(views, cam, lam, sceneDepth) {
  return views.map((v) => axisAngleDeg(v.axis, cam.axis) * Math.PI / 180
    + lam * norm(sub(v.center, cam.center)) / sceneDepth);
}

// §5.1.2: sub-region index of each view (-1 outside the angle / distance limits)
export function subRegions(cam, views, s) {
  const R = cam.R;
  return views.map((v) => {
    const d = sub(v.center, cam.center);
    const local = [dot(R[0], d), dot(R[1], d), dot(R[2], d)];
    const octant = (local[0] >= 0 ? 1 : 0) + (local[1] >= 0 ? 2 : 0) + (local[2] >= 0 ? 4 : 0);
    const ang = axisAngleDeg(v.axis, R[2]);
    const dist = norm(local);
    const aBin = Math.min(Math.floor(ang / s.max_angle * s.angle_bins), s.angle_bins - 1);
    const dBin = Math.min(Math.floor(dist / s.max_dist * s.dist_bins), s.dist_bins - 1);
    const inside = ang <= s.max_angle && dist <= s.max_dist;
    return inside ? octant * s.angle_bins * s.dist_bins + aBin * s.dist_bins + dBin : -1;
  });
}

// indices of the selected views, sorted by (d_k, k); `previous` = {R, center, selected} or null
export function selectViews(cam, views, dist, s, fallback, previous = null, available = null) {
  const n = views.length;
  const avail = available || new Array(n).fill(true);
  const region = subRegions(cam, views, s).map((r, k) => (avail[k] ? r : -1));
  const order = [...Array(n).keys()].sort((a, b) => dist[a] - dist[b] || a - b);  // stable
  const chosen = new Set();
  const seen = new Set();
  for (const k of order) {
    const r = region[k];
    if (r >= 0 && !seen.has(r)) { seen.add(r); chosen.add(k); }
  }
  if (previous && previous.selected.length) {
    const dAng = axisAngleDeg(previous.R[2], cam.R[2]);
    const dPos = norm(sub(cam.center, previous.center));
    for (const k of previous.selected) {
      if (k < 0 || k >= n || !avail[k]) continue;
      const ang = axisAngleDeg(views[k].axis, cam.R[2]);
      const d = norm(sub(views[k].center, cam.center));
      if (ang <= s.max_angle + dAng && d <= s.max_dist + dPos) chosen.add(k);
    }
  }
  let out = [...chosen];
  if (!out.length) out = order.filter((k) => avail[k]).slice(0, fallback);
  return out.sort((a, b) => dist[a] - dist[b] || a - b);
}

// Eq. 15: w_k = exp(-(d_k - d_min) / delta), floored (blend.view_weights)
export function viewWeights(d, delta, floor) {
  const dmin = Math.min(...d);
  return d.map((x) => Math.max(Math.exp(-(x - dmin) / delta), floor));
}

// what IBRModel.render does before the GL passes: selection, max_views, per_view cut, weights
export function chooseViews(cam, views, s, sel, previous = null) {
  const dist = viewDistance(views, cam, s.lam, s.scene_depth);
  let k = selectViews(cam, views, dist, s, sel.fallback, s.hysteresis ? previous : null);
  if (s.max_views > 0) k = k.slice(0, s.max_views);
  if (s.visibility === "per_view") k = k.slice(0, s.per_view_max);
  const w = viewWeights(k.map((i) => dist[i]), s.delta, sel.view_weight_floor);
  return { indices: k, weights: w, dist };
}
