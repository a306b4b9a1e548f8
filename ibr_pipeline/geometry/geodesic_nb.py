"""k geodesically nearest seeds by a multi-label Dijkstra (numba) — the fast path of
geodesic.geodesic_knn (Xu et al. §4.2.2, Eq. 2's A_i).

One priority queue of (distance, pixel, seed label): a pixel accepts the first k distinct labels
popped for it (its k nearest, in order) and only an accepted label travels on to its neighbours —
the same fixed point as the vectorised label-correcting relaxation in geodesic.py (kept as the
reference that tests/view_depth compares with), in O(k M log M) instead of one sort of every active
row per sweep (that relaxation was the largest cost of view_depth at 640x480). Hand-written because
scipy's csgraph.dijkstra gives all-pairs or single-source distances, not the k nearest of many
sources with labels.
"""
from __future__ import annotations

import heapq

import numpy as np
from numba import njit


@njit(cache=True)
def knn_dijkstra(flat_cost, h, w, idx, seed_flat, k):  # pragma: no cover - compiled
    m = idx.shape[0]
    node = np.full(h * w, -1, np.int64)
    for r in range(m):
        node[idx[r]] = r
    dist = np.full((m, k), np.inf)
    lab = np.full((m, k), -1, np.int64)
    cnt = np.zeros(m, np.int64)
    nb = np.full((m, 4), -1, np.int64)       # 4-neighbours' flat indices, -1 outside the image
    for r in range(m):
        p = idx[r]
        y, x = p // w, p % w
        if x + 1 < w:
            nb[r, 0] = p + 1
        if x > 0:
            nb[r, 1] = p - 1
        if y + 1 < h:
            nb[r, 2] = p + w
        if y > 0:
            nb[r, 3] = p - w
    heap = [(0.0, np.int64(0), np.int64(0))]
    heap.pop()
    for r in range(m):          # a seed next to a region pixel starts a path (step cost)
        for c in range(4):
            q = nb[r, c]
            if q >= 0 and seed_flat[q]:
                heapq.heappush(heap, (0.5 * (flat_cost[idx[r]] + flat_cost[q]), np.int64(r), q))
    while len(heap) > 0:
        d, r, L = heapq.heappop(heap)
        n = cnt[r]
        if n >= k:
            continue
        seen = False
        for j in range(n):
            if lab[r, j] == L:
                seen = True
                break
        if seen:
            continue
        dist[r, n] = d
        lab[r, n] = L
        cnt[r] = n + 1
        for c in range(4):
            q = nb[r, c]
            s = node[q] if q >= 0 else -1
            if s < 0 or cnt[s] >= k:
                continue
            dup = False
            for j in range(cnt[s]):
                if lab[s, j] == L:
                    dup = True
                    break
            if not dup:
                heapq.heappush(heap, (d + 0.5 * (flat_cost[idx[r]] + flat_cost[q]), s, L))
    return lab, dist
