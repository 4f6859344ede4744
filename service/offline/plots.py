"""Pictures of a building model: top-down floor plans per storey, and the descriptor's KDE bins.

Reusable pieces: `draw_floor_plan(ax, model, storey, walls=...)` draws one storey on a matplotlib axis in
the CAD frame (x right, y up, metres), so other commands can draw trajectories over it; `wall_segments_xy`
cuts the building's walls at a height into 2D segments. matplotlib is imported lazily (Agg backend).

Colours follow the paper's Figure 1: doors black, windows blue; walls light grey.
"""

from __future__ import annotations

import logging
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from macroloc.graph.descriptor import build_tables, kde_density
from macroloc.graph.features import BuildingModel, MacroFeature
from macroloc.graph.wall_mesh import load_wall_mesh, wall_segments_xy  # noqa: F401 (their old home)

log = logging.getLogger(__name__)

TYPE_COLOURS = {"door": "black", "window": "tab:blue"}
WALL_COLOUR = "0.75"
WALL_CUT_ABOVE_FLOOR_M = 1.2  # walls are cut this high above a storey's floor (through doors and windows)


def _pyplot():  # noqa: ANN202 - matplotlib.pyplot
    """pyplot on the Agg backend: imported where a picture is drawn (the backend must be chosen before pyplot is
    imported, and pyplot takes about half a second)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------- walls


def storey_cut_height_m(model: BuildingModel, storey: str | None) -> float:
    """Height (metres, CAD z) at which a storey's walls are cut: its floor (lowest door/window bottom, or the
    storey elevation) plus WALL_CUT_ABOVE_FLOOR_M."""
    skylights = [f for f in model.features if f.storey == storey and f.orientation == "horizontal"]
    feats = [f for f in model.features if f.storey == storey and f.orientation == "vertical"]
    door_bottoms = [float(f.corners_cad[:, 2].min()) for f in feats if f.type == "door"]
    window_bottoms = [float(f.corners_cad[:, 2].min()) for f in feats if f.type == "window"]
    if door_bottoms:
        floor_z = min(door_bottoms)
    elif window_bottoms:
        floor_z = min(window_bottoms) - 0.9  # a sill is about 0.9 m above the floor
    elif skylights:  # a roof: cut the walls just below its lowest skylight
        return min(float(f.corners_cad[:, 2].min()) for f in skylights) - 0.5
    else:
        floor_z = float(model.storey_elevations_m.get(str(storey), 0.0))
    return floor_z + WALL_CUT_ABOVE_FLOOR_M


# ---------------------------------------------------------------- floor plans


def short_ids(model: BuildingModel) -> dict[str, str]:
    """{feature id: 'D0', 'W3', ...}: short labels numbered per type in the model's feature order."""
    counters: Counter[str] = Counter()
    out = {}
    for f in model.features:
        out[f.id] = f"{f.type[0].upper()}{counters[f.type]}"
        counters[f.type] += 1
    return out


def storeys_of(model: BuildingModel) -> list[str | None]:
    """The storeys that hold features, in elevation order (then name)."""
    present = {f.storey for f in model.features}
    elev = model.storey_elevations_m

    def key(s: str | None) -> tuple[float, str]:
        if s is not None and s in elev:
            return elev[s], s
        zs = [float(f.centroid_cad[2]) for f in model.features if f.storey == s]
        return (min(zs) if zs else 0.0), str(s)

    return sorted(present, key=key)


def _draw_feature(ax: Any, f: MacroFeature, label: str | None, normal_len_m: float) -> None:
    colour = TYPE_COLOURS.get(f.type, "tab:red")
    c = f.corners_cad
    if f.orientation == "horizontal":  # a skylight: its outline seen from above
        ring = np.vstack([c, c[:1]])
        ax.plot(ring[:, 0], ring[:, 1], color=colour, lw=1.5, ls="--")
    else:  # the opening's bottom edge along the wall, and its normal as a tick
        ax.plot(c[:2, 0], c[:2, 1], color=colour, lw=3.0, solid_capstyle="butt")
        p, n = f.centroid_cad[:2], f.normal_cad[:2]
        ax.plot([p[0], p[0] + normal_len_m * n[0]], [p[1], p[1] + normal_len_m * n[1]], color=colour, lw=0.8)
    if label:
        ax.annotate(label, f.centroid_cad[:2], xytext=(2, 2), textcoords="offset points", fontsize=6,
                    color=colour)


def draw_floor_plan(ax: Any, model: BuildingModel, storey: str | None, walls: Any = None,
                    labels: dict[str, str] | None = None, title: bool = True) -> None:
    """Draw one storey top-down on `ax` (CAD frame x/y, metres, equal aspect).

    walls: None, a trimesh.Trimesh of the walls (cut at the storey's `storey_cut_height_m`), or an (S, 2, 2)
    array of wall segments already cut. labels: {feature id: text} (default `short_ids(model)`; {} for none).
    """
    from matplotlib.collections import LineCollection

    feats = [f for f in model.features if f.storey == storey]
    if walls is not None:
        segments = walls if isinstance(walls, np.ndarray) else wall_segments_xy(walls, storey_cut_height_m(model,
                                                                                                          storey))
        if len(segments):
            ax.add_collection(LineCollection(list(segments), colors=WALL_COLOUR, linewidths=0.8, zorder=0))
    labels = short_ids(model) if labels is None else labels
    extent = np.ptp(model.centroids_cad()[:, :2], axis=0).max() if model.features else 1.0
    for f in feats:
        _draw_feature(ax, f, labels.get(f.id), normal_len_m=0.02 * float(extent) + 0.1)
    shared = len(ax.get_shared_x_axes().get_siblings(ax)) > 1 and len(ax.get_shared_y_axes().get_siblings(ax)) > 1
    ax.set_aspect("equal", adjustable="box" if shared else "datalim")  # shared axes cannot adjust their limits
    ax.autoscale_view()
    ax.set_xlabel("x (m, CAD)")
    ax.set_ylabel("y (m, CAD)")
    if title:
        n = Counter(f.type for f in feats)
        ax.set_title(f"{storey}: {n['door']} doors, {n['window']} windows", fontsize=9)


def plot_floor_plans(model: BuildingModel, out_png: str | Path, wall_mesh: Any = None) -> Path:
    """One panel per storey (doors black, windows blue, short labels, walls grey); returns the PNG path."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    storeys = storeys_of(model)
    cols = min(2, len(storeys))
    rows = (len(storeys) + cols - 1) // cols
    lo, hi = model.centroids_cad()[:, :2].min(axis=0), model.centroids_cad()[:, :2].max(axis=0)
    aspect = (hi[1] - lo[1] + 2) / max(hi[0] - lo[0] + 2, 1e-6)
    panel_w = 7.0
    fig, axes = plt.subplots(rows, cols, figsize=(panel_w * cols, min(panel_w * aspect, 14) * rows + 0.8),
                             squeeze=False, sharex=True, sharey=True)  # storeys aligned: one CAD frame
    labels = short_ids(model)
    for ax, storey in zip(axes.ravel(), storeys, strict=False):
        draw_floor_plan(ax, model, storey, walls=wall_mesh, labels=labels)
    for ax in axes.ravel()[len(storeys):]:
        ax.axis("off")
    handles = [Line2D([], [], color=TYPE_COLOURS["door"], lw=3, label="door"),
               Line2D([], [], color=TYPE_COLOURS["window"], lw=3, label="window")]
    if wall_mesh is not None:
        handles.append(Line2D([], [], color=WALL_COLOUR, lw=1, label="walls (cut)"))
    fig.suptitle(f"{Path(model.source).name}: {len(model.features)} macro-features (top view, CAD frame)",
                 fontsize=10)
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.03, 1, 0.98))
    out = Path(out_png)
    fig.savefig(out, dpi=150)
    plt.close(fig)
    return out


# ---------------------------------------------------------------- KDE and bins (paper Figures 6 and 13)


def _kde_panel(ax: Any, samples: np.ndarray, edges: np.ndarray, scale: float, unit: str, what: str,
               domain: tuple[float, float] = (-np.inf, np.inf)) -> None:
    x = np.asarray(samples, dtype=float) * scale  # metres -> m, radians -> degrees: for a person to read
    if len(x) == 0:
        ax.text(0.5, 0.5, "no samples", transform=ax.transAxes, ha="center")
        return
    span = float(np.ptp(x)) or 1.0
    grid = np.linspace(max(x.min() - 0.05 * span, domain[0]), min(x.max() + 0.05 * span, domain[1]), 800)
    density = kde_density(samples, grid / scale) / scale  # density per displayed unit
    ax.hist(x, bins=min(60, max(10, len(x) // 5)), density=True, color="0.8", edgecolor="0.6", label="values")
    ax.plot(grid, density, color="tab:red", lw=1.5, label="Gaussian KDE (Silverman)")
    for i, e in enumerate(np.asarray(edges, dtype=float) * scale):
        ax.axvline(e, color="tab:green", lw=1, ls="--", label="bin edges" if i == 0 else None)
    ax.set_xlabel(f"{what} ({unit})")
    ax.set_ylabel("density")
    n_bins = len(edges) + 1
    ax.set_title(f"{what}: {len(x)} values, {n_bins} bin{'s' if n_bins != 1 else ''}", fontsize=9)
    ax.legend(fontsize=7)


def plot_kde_bins(model: BuildingModel, out_png: str | Path) -> Path:
    """The descriptor's look-up tables: histogram of the model's 5-NN distances and angles, their KDE and the
    bin edges at its local minima (paper Figures 6 and 13), two panels; returns the PNG path."""
    plt = _pyplot()
    tables = build_tables(model.centroids_cad())
    fig, (ax_d, ax_a) = plt.subplots(1, 2, figsize=(12, 4))
    _kde_panel(ax_d, tables.dist_samples_m, tables.dist_edges_m, 1.0, "m", "neighbour distance")
    _kde_panel(ax_a, tables.angle_samples_rad, tables.angle_edges_rad, float(np.degrees(1.0)), "deg",
               "neighbour angle", domain=(0.0, 180.0))
    fig.suptitle(f"{Path(model.source).name}: descriptor look-up tables (KDE bins)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    out = Path(out_png)
    fig.savefig(out, dpi=130)
    plt.close(fig)
    return out
