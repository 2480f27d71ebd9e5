"""Charts (PNG) and animations (GIF) of an evaluation:

- ``accuracy_vs_speed.png``: rollout MSE against forward ms per step, one numbered point per
  method and dataset (named in the legend beside the chart), marker area by parameter count, a
  method's no-hard-walls twin hollow in its colour; the solver references (the dataset's own
  solver re-run, at its ms per frame) as stars joined into the classical front, their
  predictability floor as a dotted line;
- ``error_vs_step.png``: MSE against rollout step (twins dashed in their method's colour), where
  each forward rollout fails marked;
- ``consistency_vs_k.png``: consistency and inverse MSE against the inverse steps K;
- ``forward_<dataset>.gif``: ground truth beside the R-GNS and GNS runs (fresh and pretrained)
  and the coarsest solver reference; ``forward_<dataset>_more.gif``: beside every other method;
- ``inverse_<dataset>.gif``: ground truth against each method's K inverse steps, then the
  K forward steps re-simulated from the inferred state.

Animations are grids of at most six panels a row; legends sit beside the axes, off the data.
"""
from __future__ import annotations

import io
import math
from pathlib import Path

import imageio.v2 as imageio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rgns.data.contract import KINEMATIC, atomic_path  # noqa: E402

MARKERS = "osD^v<>P*X"
PANELS_PER_ROW = 6  # an animation's grid: at most this many panels a row
NUMBER_OFFSETS = ((14, 12), (14, -12), (-14, 12), (-14, -12), (0, 18), (0, -18))  # points: numbers of close points


def write_whole(path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all (a temporary file renamed into place); a
    failed write (a full disk) raises ``OSError`` naming ``path`` and leaves no partial file."""
    try:
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(data)
    except OSError as err:
        raise OSError(err.errno, f"{path}: could not be written ({err.strerror or err}); nothing was left in its "
                                 "place") from None


def save_figure(fig, path) -> None:
    """Lay out, write a PNG at the project's resolution (whole or not at all), and free the figure."""
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=110, format="png")
    plt.close(fig)
    write_whole(path, buffer.getvalue())


TWIN = ", no hard walls"  # the label suffix of a method's twin rolled out without its hard walls


def family(label: str) -> str:
    """The method a label belongs to: its no-hard-walls twin is drawn beside it, in its colour."""
    return label.removesuffix(TWIN)


def _solvers(results: dict) -> set[str]:
    return {label for d in results["datasets"].values() for label in d.get("references", {}).get("methods", {})}


def _order(results: dict, labels) -> list[str]:
    """``labels`` in the report's order of their families, each twin right after its method, the
    solver references last."""
    families = list(dict.fromkeys(family(label) for label in results["methods"]))
    solvers = _solvers(results)
    return sorted(labels, key=lambda label: (label in solvers, families.index(family(label))
                                             if family(label) in families else len(families), label.endswith(TWIN)))


def _colours(results: dict) -> dict[str, tuple]:
    """One colour per method family (a method and its no-hard-walls twin share one), distinct
    colours for the first ten (then again); the solver references in greys."""
    solvers = _solvers(results)
    families = list(dict.fromkeys(family(label) for label in results["methods"] if label not in solvers))
    palette = [*plt.get_cmap("tab10").colors, *plt.get_cmap("Dark2").colors]
    colour = {name: palette[i % len(palette)] for i, name in enumerate(families)}
    greys = iter(str(g) for g in np.linspace(0.15, 0.65, max(len(solvers), 1)))
    colour.update({label: next(greys) for label in sorted(solvers)})
    return {label: colour[label if label in solvers else family(label)] for label in results["methods"]}


def _styles(results: dict) -> dict[str, str]:
    """Solid lines, dashed for a no-hard-walls twin; dotted for a solver reference."""
    solvers = _solvers(results)
    return {label: ":" if label in solvers else "--" if label.endswith(TWIN) else "-" for label in results["methods"]}


def _legend_outside(ax, **kwargs) -> None:
    """The legend beside the axes, off the data."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, frameon=False, **kwargs)


def _log_axes(ax, xlabel: str, ylabel: str, title: str, fontsize: int = 10) -> None:
    """An error chart's axes: log y, labels, title and a light grid."""
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=fontsize)
    ax.grid(True, which="both", alpha=0.3)


def _array(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def ms_per_frame(row: dict) -> float | None:
    """A method's forward cost per frame: ``forward_ms_per_frame`` where the evaluation recorded
    it (a stride-k model's step over k), else its ms per step (a stride-1 model, a solver's frame)."""
    value = row.get("forward_ms_per_frame")
    return row.get("forward_ms_per_step") if value is None else value


def pareto_front(points: list[tuple]) -> list[tuple]:
    """The points ``(cost, error, *anything)`` that no point of lower or equal cost beats in
    error, cheapest first."""
    kept, best = [], math.inf
    for point in sorted(points, key=lambda p: (p[0], p[1])):
        if point[1] < best:
            kept.append(point)
            best = point[1]
    return kept


def accuracy_vs_speed(results: dict, path: Path) -> bool:
    """Rollout MSE against ms per frame (a learned step over k frames, ``data.stride``, counts
    as k frames): each learned method a circle (area by parameters; its no-hard-walls twin hollow,
    in its colour) numbered on the chart and named in the legend beside it, so that no label lies
    over another; solvers as stars joined into the classical front; the learned front (the
    trained methods no cheaper trained one beats; the training-free baselines are not on it) as a
    solid line; the predictability floor dotted."""
    colours = _colours(results)
    points = [(name, label, row) for name, d in results["datasets"].items() for label, row in d["summary"].items()
              if row.get("rollout_mse") is not None and ms_per_frame(row) is not None]
    if not points:
        return False
    largest = max(row["parameters"] for _, _, row in points) or 1
    fig, ax = plt.subplots(figsize=(11, 6))
    datasets = list(results["datasets"])
    number, placed = 0, []
    order = _order(results, {label for _, label, _ in points})
    for name, label, row in sorted(points, key=lambda p: (datasets.index(p[0]), order.index(p[1]))):
        solvers = results["datasets"][name].get("references", {}).get("methods", {})
        legend = f"{label} ({name})" if len(datasets) > 1 else label
        x, y = ms_per_frame(row), row["rollout_mse"]
        if label in solvers:  # a classical solver: a star
            ax.scatter(x, y, s=160, color=colours[label], marker="*", edgecolors="black", linewidths=0.6,
                       label=f"{legend} (solver, ms / frame)", zorder=3)
            continue
        number += 1
        area = 25 + 300 * math.sqrt(row["parameters"] / largest)
        twin = label.endswith(TWIN)
        ax.scatter(x, y, s=area, marker=MARKERS[datasets.index(name) % len(MARKERS)], zorder=3,
                   facecolors="none" if twin else colours[label], edgecolors=colours[label] if twin else "black",
                   linewidths=1.4 if twin else 0.6, alpha=0.65,  # overlapping points stay visible
                   label=f"{number}: {legend} ({row['parameters'] / 1e6:.3g} M)")
        # the number on its point, or beside it with a leader where an earlier number sits there already
        here = (math.log10(max(x, 1e-12)), math.log10(max(y, 1e-30)))
        clash = sum(abs(here[0] - a) < 0.06 and abs(here[1] - b) < 0.1 for a, b in placed)
        placed.append(here)
        offset = (0, 0) if not clash else NUMBER_OFFSETS[(clash - 1) % len(NUMBER_OFFSETS)]
        ax.annotate(str(number), (x, y), textcoords="offset points", xytext=offset, ha="center", va="center",
                    fontsize=6.5, zorder=4, fontweight="bold",
                    color="white" if not clash and not twin else "black",
                    arrowprops=dict(arrowstyle="-", lw=0.5, color="0.3") if clash else None)
    for name, d in results["datasets"].items():  # each dataset's classical front, and its floor
        solvers = d.get("references", {}).get("methods", {})
        front = sorted((ms_per_frame(row), row["rollout_mse"]) for n, label, row in points
                       if n == name and label in solvers)
        if len(front) > 1:
            ax.plot(*zip(*front), color="0.35", linestyle="--", linewidth=1, zorder=2,
                    label="classical solver front" + (f" ({name})" if len(datasets) > 1 else ""))
        learned = pareto_front([(ms_per_frame(row), row["rollout_mse"]) for n, label, row in points  # trained ones
                                if n == name and label not in solvers and (row.get("parameters") or 0) > 0])
        if len(learned) > 1:
            ax.plot(*zip(*learned), color="0.1", linestyle="-", linewidth=1.2, zorder=2,
                    label="learned front" + (f" ({name})" if len(datasets) > 1 else ""))
        for label, info in solvers.items():
            mse = d["summary"].get(label, {}).get("rollout_mse")
            if info.get("perturbation") and mse is not None:
                ax.axhline(mse, color=colours[label], linestyle=":", linewidth=1,
                           label=f"predictability floor ({label}" + (f", {name})" if len(datasets) > 1 else ")"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward inference time (ms / frame; learned: median step, radius graph included, over its stride)")
    ax.set_ylabel("rollout MSE (position units²)")
    ax.set_title("Accuracy against speed (lower left is better; area ∝ parameters; hollow: without hard walls)",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.margins(0.15)
    _legend_outside(ax, markerscale=0.5)
    save_figure(fig, path)
    return True


def error_vs_step(results: dict, path: Path) -> bool:
    datasets = {n: d for n, d in results["datasets"].items() if "forward" in d}
    if not datasets:
        return False
    colours, styles = _colours(results), _styles(results)
    fig, axes = plt.subplots(len(datasets), 1, figsize=(11, 5 * len(datasets)), squeeze=False)
    for ax, (name, d) in zip(axes[:, 0], datasets.items()):
        order = _order(results, d["forward"]["methods"])
        for label in order:
            row = d["forward"]["methods"][label]
            curve = _array(row["mse_per_step"])
            steps = np.arange(1, len(curve) + 1)
            ax.plot(steps, curve, color=colours[label], linestyle=styles[label], label=label)
            if row["diverged"]:  # first broken step: stable for `stable_steps` steps
                fail = row["stable_steps"] + 1
                ax.axvline(fail, color=colours[label], linestyle="--", alpha=0.7)
                y = curve[fail - 1] if np.isfinite(curve[fail - 1]) else np.nanmax(curve)
                ax.plot([fail], [y], marker="X", markersize=11, color=colours[label], markeredgecolor="black",
                        label=f"{label} fails at step {fail}")
        s = d["forward"]["settings"]
        n = s["trajectories"]
        _log_axes(ax, "rollout step", "MSE of positions (position units²)",
                  f"{name}: error against rollout step (mean of {n} trajector{'y' if n == 1 else 'ies'} "
                  f"from frame {s['start']}; dashed: without hard walls; X: first broken step)")
        _legend_outside(ax)
    save_figure(fig, path)
    return True


def consistency_vs_k(results: dict, path: Path) -> bool:
    datasets = {n: d for n, d in results["datasets"].items() if d.get("inverse", {}).get("methods")}
    if not datasets:
        return False
    colours, styles = _colours(results), _styles(results)
    fig, axes = plt.subplots(len(datasets), 2, figsize=(15, 4.5 * len(datasets)), squeeze=False)
    for (left, right), (name, d) in zip(axes, datasets.items()):
        s = d["inverse"]["settings"]
        for label, row in d["inverse"]["methods"].items():
            horizons = [int(k) for k in row["horizons"]]
            for ax, key in ((left, "consistency_mse"), (right, "inverse_mse")):
                values = _array(r[key] for r in row["horizons"].values())
                values[values == 0] = np.nan  # exact (K <= k: frame t0 is in the velocity history)
                ax.plot(horizons, values, marker="o", color=colours[label], linestyle=styles[label], label=label)
        left.axhline(s["threshold"], color="grey", linestyle=":", label=f"stability threshold {s['threshold']:g}")
        for ax, title in ((left, "consistency MSE (inverse, then forward, at frame t0 + K)"),
                          (right, "inverse MSE at frame t0 (K <= k: exact, not drawn)")):
            _log_axes(ax, "inverse steps K", "MSE of positions (position units²)", f"{name}: {title}")
        _legend_outside(right)
    save_figure(fig, path)
    return True


def animate(panels: dict[str, np.ndarray], titles: list[str], particle_type, bounds, path: Path,
            max_frames: int, fps: float) -> None:
    """One GIF: a panel per sequence ``[F, N, D]`` (first two dimensions shown), a title per frame.

    The box is drawn with a margin of a tenth of its size around it. Particles beyond the margin
    (or not finite) are drawn in red on the margin's edge, and each panel's title counts them, so
    a rollout that breaks up does not look emptier than it is."""
    frames = len(titles)
    keep = np.unique(np.linspace(0, frames - 1, min(frames, max_frames)).round().astype(int))
    fluid = np.where(np.asarray(particle_type) == KINEMATIC, "0.55", "tab:blue")
    low, high = np.asarray(bounds, dtype=float)[:2, 0], np.asarray(bounds, dtype=float)[:2, 1]
    margin = 0.1 * (high - low)
    shown_low, shown_high = low - margin, high + margin
    columns = min(len(panels), PANELS_PER_ROW)
    rows = math.ceil(len(panels) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(2.4 * columns, 2.45 * rows + 0.3), squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.02, top=1 - 0.45 / (2.45 * rows + 0.3), wspace=0.06,
                        hspace=0.2)
    for ax in axes.flat[len(panels):]:
        ax.set_axis_off()
    axes = axes.reshape(1, -1)[:, :len(panels)]
    scatters, names = [], list(panels)
    for ax, name in zip(axes[0], names):
        scatters.append(ax.scatter([], [], s=4, c=[], clip_on=False))  # off-chart ones, on the edge, drawn whole
        ax.add_patch(plt.Rectangle(low, *(high - low), fill=False, lw=0.6, ec="0.3"))
        ax.set_xlim(shown_low[0], shown_high[0])
        ax.set_ylim(shown_low[1], shown_high[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(name, fontsize=8)
    suptitle = fig.suptitle("", fontsize=9)
    images = []
    for f in keep:
        for ax, name, scatter, sequence in zip(axes[0], names, scatters, panels.values()):
            points = np.asarray(sequence[f], dtype=float)[:, :2]
            finite = np.isfinite(points).all(axis=1)
            outside = ~finite | ((points < shown_low) | (points > shown_high)).any(axis=1)
            points = np.clip(np.nan_to_num(points, nan=shown_low[0]), shown_low, shown_high)
            scatter.set_offsets(points)
            scatter.set_color(np.where(outside, "tab:red", fluid))
            ax.set_title(f"{name} ({outside.sum()} off the chart)" if outside.any() else name, fontsize=8)
        suptitle.set_text(titles[f])
        fig.canvas.draw()
        images.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    buffer = io.BytesIO()
    imageio.mimsave(buffer, images, format="GIF", duration=1000 / fps, loop=0)
    write_whole(path, buffer.getvalue())


def headline_panels(labels: list[str], solvers: dict, most: int = PANELS_PER_ROW - 1) -> tuple[list[str], list[str]]:
    """The forward animation's panels beside the truth, and the rest (a second animation): the
    R-GNS and GNS runs (fresh and pretrained; not their no-hard-walls twins, not R-GNS†) and the
    coarsest solver reference (the half-resolution solver), at most ``most``; without any of
    those, the first ``most`` labels."""
    learned = [label for label in labels if label.startswith(("R-GNS ", "GNS ")) and not label.endswith(TWIN)]
    coarse = [label for label in labels if label in solvers and not solvers[label].get("perturbation")]
    coarse = sorted(coarse, key=lambda label: solvers[label].get("n_grid") or math.inf)[:1]
    main = (learned[:most - len(coarse)] + coarse) or labels[:most]
    return main, [label for label in labels if label not in main]


def generalise_charts(results: dict, examples: dict, out: Path) -> list[str]:
    """task=generalise: per dataset, error against step on each condition (an X at each method's
    first break over the trajectories), and per condition the state of the first
    trajectory where each method broke (or its last step), over the truth at that step in grey."""
    written = []
    for name, d in results["datasets"].items():
        conditions = {c: r for c, r in d.get("generalise", {}).get("conditions", {}).items() if "methods" in r}
        if not conditions:
            continue
        colours, styles = _colours(results), _styles(results)
        fig, axes = plt.subplots(len(conditions), 1, figsize=(11, 4 * len(conditions)), squeeze=False)
        for ax, (condition, r) in zip(axes[:, 0], conditions.items()):
            for label in _order(results, r["methods"]):
                row = r["methods"][label]
                curve = _array(row["mse_per_step"])
                colour = colours.get(label, "0.5")
                ax.plot(np.arange(1, len(curve) + 1), curve, color=colour, linestyle=styles.get(label, "-"), label=label)
                if row["first_break"]:
                    at = row["first_break"]["step"]
                    y = curve[at] if at < len(curve) and np.isfinite(curve[at]) else np.nanmax(curve)
                    ax.plot([at + 1], [y], marker="X", markersize=10, color=colour, markeredgecolor="black")
            _log_axes(ax, "rollout step", "MSE (position units²)",
                      f"{name}, {condition}: {r.get('description', '')} (X: first break)", fontsize=9)
            _legend_outside(ax)
        save_figure(fig, out / f"generalise_{name}.png")
        written.append(f"generalise_{name}.png")
        for condition, example in (examples.get(name, {}).get("generalise") or {}).items():
            if condition not in conditions or not example["predicted"]:
                continue
            labels = list(example["predicted"])
            columns = min(len(labels), PANELS_PER_ROW)
            rows = math.ceil(len(labels) / columns)
            bounds = np.asarray(example["bounds"])
            aspect = (bounds[1, 1] - bounds[1, 0]) / (bounds[0, 1] - bounds[0, 0])
            fig, axes = plt.subplots(rows, columns, figsize=(2.6 * columns, 2.6 * rows * aspect + 0.6), squeeze=False)
            kinematic = np.asarray(example["particle_type"]) == KINEMATIC
            breaks = {label: conditions[condition]["methods"][label]["breaks"][0] for label in labels}
            for ax, label in zip(axes.flat, labels):
                at, frame = example["predicted"][label]
                truth = example["truth"][label]
                ax.scatter(truth[~kinematic, 0], truth[~kinematic, 1], s=1, color="0.8")
                ax.scatter(frame[~kinematic, 0], frame[~kinematic, 1], s=1, color=colours.get(label, "C0"))
                ax.scatter(frame[kinematic, 0], frame[kinematic, 1], s=1, color="0.2")
                ax.set_xlim(*bounds[0])
                ax.set_ylim(*bounds[1])
                ax.set_aspect("equal")
                ax.set_xticks([])
                ax.set_yticks([])
                cause = breaks[label]["cause"]
                ax.set_title(f"{label}\nstep {at + 1}: {cause or 'no break'}", fontsize=7)
            for ax in list(axes.flat)[len(labels):]:
                ax.axis("off")
            fig.suptitle(f"{name}, {condition}, first trajectory: each method where it first broke, else at its "
                         "last step (grey: the truth then)", fontsize=9)
            save_figure(fig, out / f"generalise_{name}_{condition}.png")
            written.append(f"generalise_{name}_{condition}.png")
    return written


def make_all(results: dict, examples: dict, out: Path, animation) -> list[str]:
    """Write every chart and animation; the file names written, in the report's order."""
    written = []
    for name, make in (("accuracy_vs_speed.png", accuracy_vs_speed), ("error_vs_step.png", error_vs_step),
                       ("consistency_vs_k.png", consistency_vs_k)):
        if make(results, out / name):
            written.append(name)
    for dataset, example in examples.items():
        bounds = results["datasets"][dataset]["bounds"]
        forward = example.get("forward")
        if forward and forward["predicted"]:
            t0 = forward["start"]
            titles = [f"forward rollout: frame {t0 + 1 + i} (step {i + 1})" for i in range(len(forward["truth"]))]
            predicted = {k: v.numpy() for k, v in forward["predicted"].items()}
            solvers = results["datasets"][dataset].get("references", {}).get("methods", {})
            main, more = headline_panels(list(predicted), solvers)
            truth = {"ground truth": forward["truth"].numpy()}
            animate({**truth, **{k: predicted[k] for k in main}}, titles, forward["particle_type"], bounds,
                    out / f"forward_{dataset}.gif", animation.max_frames, animation.fps)
            written.append(f"forward_{dataset}.gif")
            if more:  # every other method, in a second animation
                animate({**truth, **{k: predicted[k] for k in more}}, titles, forward["particle_type"], bounds,
                        out / f"forward_{dataset}_more.gif", animation.max_frames, animation.fps)
                written.append(f"forward_{dataset}_more.gif")
        inverse = example.get("inverse")
        if inverse and inverse["inferred"]:
            t0, K, truth = inverse["start"], inverse["horizon"], inverse["truth"].numpy()  # frames t0 .. t0+K
            order = list(range(K, -1, -1)) + list(range(1, K + 1))  # back from t0+K to t0, then forward again
            titles = [f"{'inverse' if i <= K else 're-simulated'}: frame {t0 + f}" for i, f in enumerate(order)]
            panels = {"ground truth": truth[order]}
            for label, inferred in inverse["inferred"].items():
                panels[label] = np.concatenate([truth[K:], inferred.numpy(), inverse["resimulated"][label].numpy()])
            animate(panels, titles, inverse["particle_type"], bounds, out / f"inverse_{dataset}.gif",
                    animation.max_frames, animation.fps)
            written.append(f"inverse_{dataset}.gif")
    return written + generalise_charts(results, examples, out)


def views(dim: int, up: int) -> list[tuple[int, int, str]]:
    """The projections a picture shows: ``(horizontal axis, vertical axis, name)``; a 3D scene as
    seen from the front (first horizontal axis against ``up``) and from above."""
    if dim == 2:
        return [(0, 1, "")]
    across = [a for a in range(dim) if a != up]
    return [(across[0], up, "front"), (across[0], across[1], "top")]


def view_name(view: tuple[int, int, str]) -> str:
    """A view's name for a panel title, with its axes: ``front (x-y)``; empty for the 2D plane."""
    across, up, name = view
    return f"{name} ({'xyz'[across]}-{'xyz'[up]})" if name else ""


def up_axis(metadata: dict) -> int:
    """The vertical axis of a scene: the one gravity pulls along (``metadata["gravity"]``), else the second."""
    gravity = np.abs(np.asarray(metadata.get("gravity") or [0.0, 1.0], dtype=float))
    return int(np.argmax(gravity)) if gravity.any() else 1
