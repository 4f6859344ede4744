"""A layout descriptor that does not collapse: what ranks and prunes the registration's candidates (issue 37).

The paper's descriptor (`graph.descriptor`) codes the 5 nearest neighbours with KDE-minima bins; on real
buildings Silverman's KDE leaves 2 bins and the codes collide, and a single missed or false neighbour re-codes
a feature. This one keeps the information and tolerates both:

* per feature, a histogram of its neighbours within `radius_m`: (neighbour type) x (height difference bin) x
  (horizontal distance bin) x (across-wall bin: |offset . wall normal|, same wall or not); the bins are the
  building's own quantiles of those quantities (every bin used about equally often, whatever the building's
  scale), and the wall normal's sign (a convention, and unknown for an observation) does not matter. It needs
  gravity (the height difference and the horizontal distance): without it nothing is pruned;
* the feature's own width and height (a hard gate, as the hypotheses use it, and a tie-break).

An observation's histogram is built the same way from the other observations around it (its rectangle gives
the wall normal), each neighbour in exactly one bin. A CAD feature's histogram is *dilated*: each neighbour
counts in every bin its tolerance box (`tolerance_m` on each quantity: the observation noise) touches. The
score of a CAD candidate is one-sided: how many of the observed neighbours its layout explains,
`sum_b min(obs_b, cad_dilated_b)`, each weighted by how rare its bin is among the building's features
(-log of the fraction that have it: a relation every feature has tells nothing). Missed neighbours (dropped,
or beyond what was observed) cost nothing; a false one costs every candidate alike.
Frames: CAD / gravity-aligned map, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class LayoutParams:
    radius_m: float = 12.0  # neighbours counted within this 3-D distance
    dz_bins: int = 12  # quantile bins of the height difference (signed)
    distance_bins: int = 48  # quantile bins of the horizontal distance
    across_bins: int = 3  # |offset . normal|: bin 0 below same_wall_m, then quantile bins
    same_wall_m: float = 0.4
    tolerance_m: float = 0.25  # a CAD neighbour counts in every bin within this of its values (each quantity)
    n_types: int = 2

    @property
    def n_bins(self) -> int:
        return self.n_types * self.dz_bins * self.distance_bins * self.across_bins


@dataclass(frozen=True)
class Layout:
    """Per CAD feature: `dilated` (N, B) uint8, its neighbours' bin counts with the tolerance (module doc; at most
    255); the bin edges to code observations with."""

    dilated: np.ndarray
    weight: np.ndarray  # (B,) -log of the fraction of features whose dilated histogram has the bin: rare counts more
    dz_edges: np.ndarray
    d_edges: np.ndarray
    w_edges: np.ndarray
    params: LayoutParams

    def code(self, offsets: np.ndarray, normal: np.ndarray, types: np.ndarray, slack: np.ndarray | None = None
             ) -> np.ndarray:
        """Bin index of neighbour offsets (K, 3) (z up) from a feature with unit `normal` (3,) or (K, 3),
        neighbour type codes (K,); `slack` (3,): added to (dz, horizontal distance, across) first."""
        dz, d, w = _quantities(offsets, np.broadcast_to(normal, offsets.shape))
        if slack is not None:
            dz, d, w = dz + slack[0], d + slack[1], np.maximum(w + slack[2], 0.0)
        p = self.params
        zb = np.searchsorted(self.dz_edges, dz)
        db = np.searchsorted(self.d_edges, d)
        wb = np.searchsorted(self.w_edges, w)
        return ((types.astype(np.int64) * p.dz_bins + zb) * p.distance_bins + db) * p.across_bins + wb

    def histogram(self, offsets: np.ndarray, normal: np.ndarray, types: np.ndarray) -> np.ndarray:
        """The (B,) histogram of one feature's neighbours (offsets (K, 3), z up, within radius_m)."""
        return np.bincount(self.code(offsets, normal, types), minlength=self.params.n_bins)

    def scores(self, obs_hist: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """How many of the observed neighbours (histogram (B,)) each CAD candidate's layout explains."""
        nz = np.flatnonzero(obs_hist)
        if not len(nz) or not len(cand):
            return np.zeros(len(cand), dtype=np.int64)
        return (np.minimum(obs_hist[nz][None, :], self.dilated[np.ix_(cand, nz)]) * self.weight[nz]).sum(axis=1)

    def explained(self, obs_hist: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """How many of the observed neighbours each candidate's layout explains (unweighted)."""
        nz = np.flatnonzero(obs_hist)
        if not len(nz) or not len(cand):
            return np.zeros(len(cand), dtype=np.int64)
        return np.minimum(obs_hist[nz][None, :], self.dilated[np.ix_(cand, nz)]).sum(axis=1)


def _quantities(offsets: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height difference, horizontal distance, and |offset . horizontal normal| of offsets (K, 3)."""
    n_h = normals.copy()
    n_h[:, 2] = 0.0
    n_h /= np.maximum(np.linalg.norm(n_h, axis=1), 1e-9)[:, None]
    return offsets[:, 2], np.linalg.norm(offsets[:, :2], axis=1), np.abs(np.einsum("ki,ki->k", offsets, n_h))


def _edges(values: np.ndarray, bins: int, fallback_hi: float, min_width: float) -> np.ndarray:
    """Quantile bin edges, none closer than `min_width` to the previous one (then the tolerance box of a value,
    +-min_width, touches at most 3 bins, and sampling it at -, 0, + finds every one)."""
    q = np.quantile(values, np.linspace(0, 1, bins + 1)[1:-1]) if len(values) else \
        np.linspace(0.0, fallback_hi, bins + 1)[1:-1]
    if not len(q):
        return q
    kept = [float(q[0])]
    for e in q[1:]:
        if e - kept[-1] >= min_width:
            kept.append(float(e))
    return np.array(kept)


def build_layout(centroids: np.ndarray, normals: np.ndarray, type_codes: np.ndarray,
                 params: LayoutParams | None = None, tree: cKDTree | None = None) -> Layout:
    """The layout histograms of a building's features (see the module doc)."""
    p = params or LayoutParams()
    n = len(centroids)
    tree = tree if tree is not None else cKDTree(centroids)
    pairs = tree.query_pairs(p.radius_m, output_type="ndarray") if n > 1 else np.zeros((0, 2), dtype=np.int64)
    i = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    j = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    off = centroids[j] - centroids[i]
    dz, d, w = _quantities(off, normals[i])
    far = w[w >= p.same_wall_m]
    tol = p.tolerance_m
    w_edges = _edges(far, p.across_bins - 1, p.radius_m, tol)
    w_edges = np.concatenate([[p.same_wall_m], w_edges[w_edges >= p.same_wall_m + tol]])
    layout = Layout(np.zeros((n, p.n_bins), dtype=np.uint8), np.zeros(p.n_bins), _edges(dz, p.dz_bins, p.radius_m, tol),
                    _edges(d, p.distance_bins, p.radius_m, tol), w_edges, p)
    if len(i):
        steps = np.array([[a, b, c] for a in (-tol, 0.0, tol) for b in (-tol, 0.0, tol) for c in (-tol, 0.0, tol)])
        codes = np.stack([layout.code(off, normals[i], type_codes[j], slack=s) for s in steps], axis=1)
        codes.sort(axis=1)
        first = np.ones(codes.shape, dtype=bool)
        first[:, 1:] = codes[:, 1:] != codes[:, :-1]  # each bin once per neighbour
        rows = np.broadcast_to(i[:, None], codes.shape)[first]
        keys, counts = np.unique(rows * p.n_bins + codes[first], return_counts=True)
        layout.dilated.reshape(-1)[keys] = np.minimum(counts, 255)
    layout.weight[:] = -np.log(((layout.dilated > 0).sum(axis=0) + 1.0) / (n + 1.0))
    return layout
