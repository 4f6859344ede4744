"""Registering observed macro-features (map frame) to the building model (CAD frame): T_cad_map.

Two methods behind one entry point, `register()`:

* `paper`  — the paper's algorithm exactly (§2.3.2): top-1 Hamming match per observed feature, RANSAC on
  4-point minimal sets with the coplanarity test (eq. 10, eps = 0.01), the hypothesis count of eq. (9),
  the weighted SVD fit (eqs. 11–17), and a final refinement with all corners. It never says `ambiguous`.
* `robust` (default) — see `graph/robust.py`: pose hypotheses from single door/window rectangles against
  every size-compatible CAD feature, gravity when known, verification by all observations, refinement, and
  an explicit test for a second, different pose that explains the observations about as well
  (-> `ambiguous`, never a guess).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from macroloc.graph.descriptor import describe, match_top_k
from macroloc.graph.errors import UserInputError
from macroloc.graph.features import BuildingModel
from macroloc.graph.model_index import ModelIndex, index_for
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.registration_types import RegistrationResult, corner_correspondences, majority_storey
from macroloc.graph.rigid import make_T, weighted_rigid_fit
from macroloc.graph.robust import RobustParams, register_robust
from macroloc.graph.robust import prepare as prepare_robust

__all__ = ["METHODS", "PaperParams", "RegistrationResult", "corner_correspondences", "descriptor_matches",
           "hypothesis_count", "majority_storey", "register", "register_paper"]

METHODS = ("robust", "paper")


@dataclass(frozen=True)
class PaperParams:
    inlier_threshold_m: float = 0.30
    success_probability: float = 0.99  # p of eq. (9)
    coplanarity_eps: float = 0.01  # eq. (10)
    max_hypotheses: int = 10000
    min_inliers: int = 4
    seed: int = 0


def register(model: BuildingModel, obs: ObservationSet, method: str = "robust",
             params: RobustParams | PaperParams | None = None, **overrides: float) -> RegistrationResult:
    """Estimate T_cad_map from observations in the map frame. See the module docstring for the methods.
    `params`: the method's typed parameters (None: its defaults); `overrides`: fields of them to change by name
    (the CLI's and the config's, e.g. `inlier_threshold_m=0.3`)."""
    if method not in METHODS:
        raise UserInputError(f"unknown method {method!r} (expected one of {', '.join(METHODS)})")
    kind = PaperParams if method == "paper" else RobustParams
    if params is not None and not isinstance(params, kind):
        raise TypeError(f"method {method!r} takes {kind.__name__}, not {type(params).__name__}")
    chosen = kind(**overrides) if params is None else replace(params, **overrides)  # type: ignore[arg-type]
    # pre-processing (per building and storey hint, cached on disk: graph.model_index), not part of the registration
    # time: nothing in the timed block below builds what depends on the building alone
    index = index_for(model)
    if obs.storey_hint is not None:
        if obs.storey_hint not in set(index.storeys.tolist()):
            raise UserInputError(f"hints.storey {obs.storey_hint!r} is not a storey of this building "
                                 f"({', '.join(sorted(set(index.storeys.tolist())))})")
        index = index.for_storey(obs.storey_hint)
    if isinstance(chosen, RobustParams):
        prepare_robust(index, chosen)
    t0 = time.perf_counter()
    if isinstance(chosen, PaperParams):
        result = register_paper(index, obs.observations, chosen)
    else:
        result = register_robust(index, obs, chosen)
    result.elapsed_ms = (time.perf_counter() - t0) * 1000.0
    return result


# ----------------------------------------------------------------------------- the paper's method

def _coplanar(p: np.ndarray, eps: float) -> bool:
    """eq. (10): |(x3 - x1) . [(x2 - x1) x (x4 - x1)]| < eps."""
    return abs(float(np.dot(p[2] - p[0], np.cross(p[1] - p[0], p[3] - p[0])))) < eps


def hypothesis_count(p: float, w: float, m: int = 4) -> float:
    """eq. (9): N = log(1 - p) / log(1 - w^m)."""
    wm = w**m
    if wm <= 0.0:
        return np.inf
    if wm >= 1.0:
        return 1.0
    return float(np.log(1.0 - p) / np.log(1.0 - wm))


def _batched_rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """eqs. (11)–(17) with unit weights for a batch of point sets a, b (H, m, 3): R (H, 3, 3), t (H, 3)."""
    a_bar, b_bar = a.mean(axis=1), b.mean(axis=1)
    S = np.einsum("hni,hnj->hij", a - a_bar[:, None], b - b_bar[:, None])  # eq. (14)
    U, _, Vt = np.linalg.svd(S)  # eq. (15)
    V = np.swapaxes(Vt, 1, 2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, 1, 2)))
    D = np.zeros((len(a), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(d == 0, 1.0, d)
    R = V @ D @ np.swapaxes(U, 1, 2)  # eq. (16), reflection-safe
    return R, b_bar - np.einsum("hij,hj->hi", R, a_bar)  # eq. (17)


def register_paper(index: ModelIndex, obs: list[Observation], params: PaperParams) -> RegistrationResult:
    """§2.3.2 exactly: top-1 descriptor match, 4-point RANSAC with eqs. (9), (10), SVD fit, corner refinement.

    Hypotheses are drawn and scored in blocks (vectorised); after each block N is re-estimated by eq. (9)
    from the best inlier ratio so far, exactly as a sequential adaptive RANSAC would stop.
    """
    n = len(obs)
    if n < 4 or len(index.features) < 4:
        return RegistrationResult("not_localized", None, [], 0, None, diagnostics={"reason": "fewer than 4"})
    c_obs = np.array([o.centroid_map for o in obs])
    codes = describe(c_obs, [o.type for o in obs], index.tables)
    best_idx, _ = match_top_k(codes, index.codes, k=1)
    match = best_idx[:, 0]
    c_cad = index.centroids[match]
    rng = np.random.default_rng(params.seed)
    best_T, best_inl = None, np.zeros(n, dtype=bool)
    n_needed, drawn, block = float(params.max_hypotheses), 0, 256
    while drawn < min(n_needed, params.max_hypotheses):
        samples = np.argsort(rng.random((block, n)), axis=1)[:, :4]
        drawn += block
        p = c_obs[samples]
        triple = np.einsum("hi,hi->h", p[:, 2] - p[:, 0], np.cross(p[:, 1] - p[:, 0], p[:, 3] - p[:, 0]))
        m_sorted = np.sort(match[samples], axis=1)
        distinct = np.all(np.diff(m_sorted, axis=1) != 0, axis=1)
        ok = distinct & (np.abs(triple) >= params.coplanarity_eps)  # eq. (10): coplanar sets are rejected
        if not ok.any():
            continue
        R, t = _batched_rigid_fit(p[ok], c_cad[samples[ok]])
        moved = np.einsum("hij,nj->hni", R, c_obs) + t[:, None, :]
        inl = np.linalg.norm(moved - c_cad[None], axis=2) < params.inlier_threshold_m
        h = int(np.argmax(inl.sum(axis=1)))
        if inl[h].sum() > best_inl.sum():
            best_T, best_inl = make_T(R[h], t[h]), inl[h]
            n_needed = hypothesis_count(params.success_probability, best_inl.sum() / n)  # eq. (9)
    if best_T is None or best_inl.sum() < params.min_inliers:
        return RegistrationResult("not_localized", None, [], int(best_inl.sum()), None,
                                  diagnostics={"hypotheses": drawn})
    pairs = [(int(i), int(match[i])) for i in np.flatnonzero(best_inl)]
    src, dst = corner_correspondences(best_T, obs, pairs, index)
    T = weighted_rigid_fit(src, dst)  # final refinement with all the corners
    return RegistrationResult(
        "localized", T, [(i, index.features[j].id) for i, j in pairs], len(pairs),
        majority_storey(index, [j for _, j in pairs]), diagnostics={"hypotheses": drawn})


def descriptor_matches(index: ModelIndex, obs: list[Observation]) -> list[tuple[int, str]]:
    """The paper's Table 1 matches: top-1 Hamming match of every observed feature, before RANSAC."""
    codes = describe(np.array([o.centroid_map for o in obs]), [o.type for o in obs], index.tables)
    best_idx, _ = match_top_k(codes, index.codes, k=1)
    return [(i, index.features[int(j)].id) for i, j in enumerate(best_idx[:, 0])]
