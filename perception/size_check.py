"""The building checks the detector: a reconstructed opening must have the size of one of the model's doors or
windows (issue 32).

The model's sizes come in as plain data (`OpeningSizes`, built by the caller from the BIM's features: perception
never reads the building). A dimension the image shows whole is compared both ways, within the chain's measured
error at that depth (`SizeTolerance`); a dimension cut by the image border is only a lower bound (the visible part
of an opening is never larger than the opening), so it is compared one way. The width and the height must fit the
same model size.

Door or window: the opening takes the kind of the nearest model size that fits, re-typed where that is the other
kind (`retyped_from`), the detector's kind winning a tie. The metric size is evidence the image classifier lacks:
a detector may call most door-sized openings "window" (docs/measurements.md, "The detector's kind and the size
tolerance"); kept as windows they would lose their corners downstream, dropped they would be lost.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from macroloc.perception.params import SizeTolerance

__all__ = ["KINDS", "OpeningSizes", "SizeStatus", "SizeTolerance"]  # SizeTolerance: perception.params

SizeStatus = Literal["confirmed", "rejected", "unchecked"]
KINDS = ("door", "window")


@dataclass(frozen=True)
class OpeningSizes:
    """The distinct sizes of a model's openings: (kind, width_m, height_m), kind "door" or "window"."""

    sizes: tuple[tuple[str, float, float], ...]

    @staticmethod
    def of(openings: Iterable[tuple[str, float, float]], round_m: float = 0.01) -> OpeningSizes:
        """Distinct sizes (rounded to `round_m`) of (kind, width_m, height_m) triples, sorted."""
        seen = {(k, round(w / round_m) * round_m, round(h / round_m) * round_m) for k, w, h in openings}
        return OpeningSizes(tuple(sorted(seen)))

    def wh_m(self, kind: str) -> np.ndarray:
        """(N, 2) width, height of the model's openings of `kind`, metres."""
        return np.array([(w, h) for k, w, h in self.sizes if k == kind], float).reshape(-1, 2)


@dataclass(frozen=True)
class SizeVerdict:
    """The size check of one opening: status, the kind it was checked as, the model size it fits (width, height,
    m) or None, which dimensions were compared both ways (width, height), and its type before a re-typing."""

    status: SizeStatus
    kind: str
    matched_wh_m: tuple[float, float] | None = None
    whole: tuple[bool, bool] = (False, False)
    retyped_from: str | None = None
    reason: str = ""

    def to_json(self) -> dict[str, object]:
        out: dict[str, object] = {"size_check": self.status}
        if self.matched_wh_m is not None:
            out["model_size_m"] = [round(v, 3) for v in self.matched_wh_m]
        if self.retyped_from is not None:
            out["retyped_from"] = self.retyped_from
        if self.reason:
            out["size_reason"] = self.reason
        return out


UNCHECKED = SizeVerdict("unchecked", "")


def fitting(wh_m: np.ndarray, width_m: float | np.ndarray, height_m: float | np.ndarray,
            tol_m: float | np.ndarray, truncated: tuple[bool, bool] | np.ndarray) -> np.ndarray:
    """Which model sizes (N, 2) a measured size fits: |measured - model| <= tol on a whole dimension,
    measured <= model + tol on one cut by the border (sideways cuts the width, vertically the height).
    Scalars give (N,); M measurements (width, height, tol (M,), truncated (M, 2)) give (M, N)."""
    meas = np.stack(np.broadcast_arrays(np.asarray(width_m, float), np.asarray(height_m, float)), axis=-1)
    cut = np.broadcast_to(np.asarray(truncated, bool), meas.shape)
    diff = meas[..., None, :] - wh_m  # (..., N, 2)
    tol = np.asarray(tol_m, float)[..., None, None]
    ok = np.where(cut[..., None, :], diff <= tol, np.abs(diff) <= tol)
    return np.asarray(ok.all(axis=-1))


def check_size(kind: str, width_m: float, height_m: float, depth_m: float, truncated: tuple[bool, bool],
               sizes: OpeningSizes | None, tol: SizeTolerance | None = None) -> SizeVerdict:
    """The verdict on an opening of `kind` measured `width_m` x `height_m` at `depth_m` (mean corner depth, m).

    confirmed: a whole dimension fits a model size; the kind becomes that of the nearest fitting size (re-typed
    where it is the other kind); rejected: no model size of either kind fits; unchecked: no sizes given, or both
    dimensions cut by the border and some size still fits their lower bounds."""
    if sizes is None or not sizes.sizes:
        return SizeVerdict("unchecked", kind)
    tol = tol or SizeTolerance()
    tol_m = tol.at(depth_m)
    whole = (not truncated[0], not truncated[1])
    best: tuple[float, str, tuple[float, float]] | None = None
    for k in KINDS:
        wh = sizes.wh_m(k)
        ok = fitting(wh, width_m, height_m, tol_m, truncated)
        if ok.any():
            misfit, size = _nearest(wh[ok], width_m, height_m, whole)
            if best is None or misfit < best[0] or (misfit == best[0] and k == kind):
                best = (misfit, k, size)
    if best is None:
        return SizeVerdict("rejected", kind, None, whole,
                           reason=f"{width_m:.2f} x {height_m:.2f} m fits no model door or window within {tol_m:.2f} m"
                           + (" (cut by the border)" if not all(whole) else ""))
    _, k, size = best
    return SizeVerdict("confirmed" if any(whole) else "unchecked", k, size, whole, None if k == kind else kind)


def _nearest(wh_m: np.ndarray, width_m: float, height_m: float,
             whole: tuple[bool, bool]) -> tuple[float, tuple[float, float]]:
    """(misfit, size) of the model size nearest the measurement: the larger misfit of its whole dimensions (0
    where none is whole: any size that fits the lower bounds is as near)."""
    use = np.array(whole, bool)
    d = np.abs(wh_m - np.array([width_m, height_m]))[:, use].max(axis=1) if use.any() else np.zeros(len(wh_m))
    i = int(np.argmin(d))
    return float(d[i]), (float(wh_m[i, 0]), float(wh_m[i, 1]))
