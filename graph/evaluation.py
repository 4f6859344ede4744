"""The project's own localization evaluation: seeded scenarios drawn from a building, both methods side by side.

A scenario (scenario i of seed s uses np.random.default_rng([s, i])): pick a storey with >= 4 features and a
start feature on it; keep the K nearest features (K from `k_choices`); drop each with probability `drop`
(at least 4 kept); flip door<->window with probability `flip`; add N(0, sigma^2) to every corner; add
round(fp x K) false doors/windows on the wall line of an observed feature, away from real ones; move all by a
random rigid T_map_cad (variant 'gravity': yaw + shift, gravity given; 'full': any rotation, gravity given;
'nogravity': any rotation, no gravity); shuffle corners and features.

Ground truth of ambiguity: a scenario is *genuinely ambiguous* when the robust registration, given the
noise-free true observations in the CAD frame itself, finds a second, different pose explaining them all
equally well (`ambiguous`) — no localizer can tell those poses apart from doors and windows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from macroloc.graph.features import BuildingModel
from macroloc.graph.observations import Observation, ObservationSet
from macroloc.graph.registration import RegistrationResult, register
from macroloc.graph.rigid import apply, invert, make_T, rot_z, rotation_angle_deg

SUCCESS_ROT_DEG, SUCCESS_TRANS_M, WRONG_TRANS_M = 2.0, 0.15, 0.5
OTHER = {"door": "window", "window": "door"}


@dataclass(frozen=True)
class ScenarioParams:
    variant: str = "gravity"
    k_choices: tuple[int, ...] = (6, 10, 20, 30)
    sigma_m: float = 0.05
    drop: float = 0.15
    flip: float = 0.05
    fp: float = 0.10
    max_translation_m: float = 50.0


@dataclass
class Scenario:
    obs: ObservationSet
    T_cad_map: np.ndarray
    truth_ids: list[list[str] | None]  # per observation: acceptable CAD ids, None for a false positive
    true_centroids_cad: np.ndarray  # (n_true, 3)
    storey: str
    clean_obs_cad: ObservationSet  # noise-free true observations in the CAD frame (for the ambiguity truth)


def _random_rotation(rng: np.random.Generator, variant: str) -> np.ndarray:
    if variant == "gravity":
        return rot_z(rng.uniform(0, 2 * np.pi))
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_scenario(model: BuildingModel, index: int, seed: int, p: ScenarioParams) -> Scenario:
    rng = np.random.default_rng([seed, index])
    by_storey = {s: fs for s, fs in model.by_storey().items() if len(fs) >= 4}
    storeys = sorted(by_storey, key=str)
    storey = storeys[rng.integers(len(storeys))]
    pool = by_storey[storey]
    start = pool[rng.integers(len(pool))]
    k = min(int(rng.choice(p.k_choices)), len(pool))
    dxy = np.linalg.norm(np.array([f.centroid_cad[:2] for f in pool]) - start.centroid_cad[:2], axis=1)
    chosen = [pool[i] for i in np.argsort(dxy, kind="stable")[:k]]
    keep = rng.random(k) >= p.drop
    if keep.sum() < 4:
        keep[rng.permutation(np.flatnonzero(~keep))[: 4 - keep.sum()]] = True
    observed = [f for f, kept in zip(chosen, keep, strict=True) if kept]
    entries: list[tuple[str, np.ndarray, list[str] | None]] = []
    for f in observed:
        kind = OTHER[f.type] if rng.random() < p.flip else f.type
        entries.append((kind, f.corners_cad + rng.normal(0, p.sigma_m, (4, 3)), [f.id, *f.duplicates]))
    all_xy = np.array([f.centroid_cad[:2] for f in model.features])
    for _ in range(int(np.floor(p.fp * k + 0.5))):
        anchor = observed[rng.integers(len(observed))]
        u = np.cross([0.0, 0.0, 1.0], anchor.normal_cad)
        u = u / np.linalg.norm(u) if np.linalg.norm(u) > 0.5 else np.array([1.0, 0.0, 0.0])
        kind = str(rng.choice(["door", "window"]))
        w, h = (0.9, 2.1) if kind == "door" else (1.2, 1.2)
        for _attempt in range(50):
            xy = anchor.centroid_cad[:2] + rng.choice([-1, 1]) * rng.uniform(1.5, 6.0) * u[:2]
            if np.min(np.linalg.norm(all_xy - xy, axis=1)) >= 1.0:
                break
        floor = min(c[2] for f in observed for c in f.corners_cad)
        centre = np.array([xy[0], xy[1], floor + (h / 2 if kind == "door" else 0.9 + h / 2)])
        corners = np.array([centre + a * w / 2 * u + b * h / 2 * np.array([0, 0, 1.0])
                            for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        entries.append((kind, corners + rng.normal(0, p.sigma_m, (4, 3)), None))
    R = _random_rotation(rng, p.variant)
    d = rng.normal(size=3)
    T_map_cad = make_T(R, d / np.linalg.norm(d) * rng.uniform(0, p.max_translation_m))
    obs, truth = [], []
    for i in rng.permutation(len(entries)):
        kind, corners, ids = entries[i]
        c_map = apply(T_map_cad, corners[rng.permutation(4)])
        obs.append(Observation(kind, c_map.mean(axis=0), c_map))
        truth.append(ids)
    gravity = None if p.variant == "nogravity" else R @ np.array([0.0, 0.0, -1.0])
    clean = ObservationSet([Observation(f.type, f.centroid_cad, f.corners_cad) for f in observed],
                           np.array([0.0, 0.0, -1.0]))
    return Scenario(ObservationSet(obs, gravity), invert(T_map_cad), truth,
                    np.array([f.centroid_cad for f in observed]), str(storey), clean)


@dataclass
class Outcome:
    status: str
    outcome: str  # success | wrong | imprecise | ambiguous | not_localized
    correct: int
    incorrect: int
    n_obs: int
    elapsed_ms: float
    genuinely_ambiguous: bool = False


def score(s: Scenario, r: RegistrationResult, genuinely_ambiguous: bool) -> Outcome:
    correct = sum(1 for i, fid in r.matches if fid in (s.truth_ids[i] or []))
    out = Outcome(r.status, r.status, correct, len(r.matches) - correct, len(s.truth_ids), r.elapsed_ms,
                  genuinely_ambiguous)
    if r.status == "localized" and r.T_cad_map is not None:
        rot = rotation_angle_deg(r.T_cad_map[:3, :3] @ s.T_cad_map[:3, :3].T)
        p_map = apply(invert(s.T_cad_map), s.true_centroids_cad)
        err = float(np.linalg.norm(apply(r.T_cad_map, p_map) - s.true_centroids_cad, axis=1).max())
        out.outcome = ("success" if rot < SUCCESS_ROT_DEG and err < SUCCESS_TRANS_M
                       else "wrong" if err > WRONG_TRANS_M else "imprecise")
    return out


@dataclass
class Summary:
    method: str
    outcomes: list[Outcome] = field(default_factory=list)

    def rate(self, kind: str, group: bool | None = None) -> float | None:
        rs = [o for o in self.outcomes if group is None or o.genuinely_ambiguous == group]
        return 100.0 * sum(o.outcome == kind for o in rs) / len(rs) if rs else None

    def to_json(self) -> dict:
        ms = [o.elapsed_ms for o in self.outcomes]
        returned = sum(o.correct + o.incorrect for o in self.outcomes)
        return {
            "method": self.method, "n": len(self.outcomes),
            **{f"{k}_pct": self.rate(k) for k in ("success", "wrong", "imprecise", "ambiguous", "not_localized")},
            "unambiguous_success_pct": self.rate("success", False),
            "unambiguous_wrong_pct": self.rate("wrong", False),
            "genuinely_ambiguous_n": sum(o.genuinely_ambiguous for o in self.outcomes),
            "honest_ambiguous_pct": self.rate("ambiguous", True),
            "match_precision_pct": 100.0 * sum(o.correct for o in self.outcomes) / returned if returned else None,
            "elapsed_ms_median": float(np.median(ms)) if ms else None,
            "elapsed_ms_p95": float(np.percentile(ms, 95)) if ms else None,
        }


def evaluate(model: BuildingModel, n: int, seed: int, params: ScenarioParams,
             methods: tuple[str, ...] = ("paper", "robust"), progress=None) -> dict[str, Summary]:
    """Run every method on the same n scenarios; returns a Summary per method."""
    summaries = {m: Summary(m) for m in methods}
    for i in range(n):
        s = make_scenario(model, i, seed, params)
        ambiguous_truth = register(model, s.clean_obs_cad).status == "ambiguous"
        for m in methods:
            summaries[m].outcomes.append(score(s, register(model, s.obs, method=m), ambiguous_truth))
        if progress is not None:
            progress(i + 1)
    return summaries
