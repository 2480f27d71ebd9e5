"""Charts (PNG) and animations (GIF) of an evaluation:

- ``accuracy_vs_speed.png``: rollout MSE against forward ms per step, one point per method and
  dataset, marker area by parameter count; the solver references (the dataset's own solver
  re-run, at its ms per frame) as stars joined into the classical front, their predictability
  floor as a dotted line;
- ``error_vs_step.png``: MSE against rollout step, where each forward rollout fails marked;
- ``consistency_vs_k.png``: consistency and inverse MSE against the inverse steps K;
- ``forward_<dataset>.gif``: ground truth against each method's forward rollout;
- ``inverse_<dataset>.gif``: ground truth against each method's K inverse steps, then the
  K forward steps re-simulated from the inferred state.
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
LINESTYLES = ("-", "--", "-.", ":")


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


def _colours(results: dict) -> dict[str, tuple]:
    cmap = plt.get_cmap("tab10")
    return {label: cmap(i % 10) for i, label in enumerate(results["methods"])}


def _styles(results: dict) -> dict[str, str]:
    """Line styles that keep overlapping curves of different methods apart."""
    return {label: LINESTYLES[i % len(LINESTYLES)] for i, label in enumerate(results["methods"])}


def _array(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def accuracy_vs_speed(results: dict, path: Path) -> bool:
    colours = _colours(results)
    points = [(name, label, row) for name, d in results["datasets"].items() for label, row in d["summary"].items()
              if row.get("rollout_mse") is not None and row.get("forward_ms_per_step") is not None]
    if not points:
        return False
    largest = max(row["parameters"] for _, _, row in points) or 1
    fig, ax = plt.subplots(figsize=(7, 5))
    datasets = list(results["datasets"])
    for name, label, row in points:
        solvers = results["datasets"][name].get("references", {}).get("methods", {})
        legend = f"{label} ({name})" if len(datasets) > 1 else label
        if label in solvers:  # a classical solver: a star, annotated without parameters
            ax.scatter(row["forward_ms_per_step"], row["rollout_mse"], s=220, color=colours[label], marker="*",
                       edgecolors="black", linewidths=0.6, label=f"{legend} (solver, ms / frame)", zorder=3)
            ax.annotate(label, (row["forward_ms_per_step"], row["rollout_mse"]), textcoords="offset points",
                        xytext=(8, -10), fontsize=8)
            continue
        area = 40 + 600 * math.sqrt(row["parameters"] / largest)
        ax.scatter(row["forward_ms_per_step"], row["rollout_mse"], s=area, color=colours[label],
                   marker=MARKERS[datasets.index(name) % len(MARKERS)], alpha=0.75, edgecolors="black", label=legend)
        ax.annotate(f"{label}\n{row['parameters'] / 1e6:.3g} M params", (row["forward_ms_per_step"], row["rollout_mse"]),
                    textcoords="offset points", xytext=(8, 6), fontsize=8)
    for name, d in results["datasets"].items():  # each dataset's classical front, and its floor
        solvers = d.get("references", {}).get("methods", {})
        front = sorted((row["forward_ms_per_step"], row["rollout_mse"]) for n, label, row in points
                       if n == name and label in solvers)
        if len(front) > 1:
            ax.plot(*zip(*front), color="0.35", linestyle="--", linewidth=1, zorder=2,
                    label="classical solver front" + (f" ({name})" if len(datasets) > 1 else ""))
        for label, info in solvers.items():
            mse = d["summary"].get(label, {}).get("rollout_mse")
            if info.get("perturbation") and mse is not None:
                ax.axhline(mse, color=colours[label], linestyle=":", linewidth=1,
                           label=f"predictability floor ({label}" + (f", {name})" if len(datasets) > 1 else ")"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward inference time (ms / step, median, radius graph included; solvers: ms / frame)")
    ax.set_ylabel("rollout MSE (position units²)")
    ax.set_title("Accuracy against speed (lower left is better; marker area ∝ parameters)")
    ax.grid(True, which="both", alpha=0.3)
    ax.margins(0.25)
    ax.legend(fontsize=8, markerscale=0.5, loc="best")
    save_figure(fig, path)
    return True


def error_vs_step(results: dict, path: Path) -> bool:
    datasets = {n: d for n, d in results["datasets"].items() if "forward" in d}
    if not datasets:
        return False
    colours, styles = _colours(results), _styles(results)
    fig, axes = plt.subplots(1, len(datasets), figsize=(7 * len(datasets), 4.8), squeeze=False)
    for ax, (name, d) in zip(axes[0], datasets.items()):
        for label, row in d["forward"]["methods"].items():
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
        ax.set_yscale("log")
        ax.set_xlabel("rollout step")
        ax.set_ylabel("MSE of positions (position units²)")
        n = s["trajectories"]
        ax.set_title(f"{name}: error against rollout step\n(mean of {n} trajector{'y' if n == 1 else 'ies'} "
                     f"from frame {s['start']}; X: first broken step)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    save_figure(fig, path)
    return True


def consistency_vs_k(results: dict, path: Path) -> bool:
    datasets = {n: d for n, d in results["datasets"].items() if d.get("inverse", {}).get("methods")}
    if not datasets:
        return False
    colours, styles = _colours(results), _styles(results)
    fig, axes = plt.subplots(len(datasets), 2, figsize=(12, 4.5 * len(datasets)), squeeze=False)
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
            ax.set_yscale("log")
            ax.set_xlabel("inverse steps K")
            ax.set_ylabel("MSE of positions (position units²)")
            ax.set_title(f"{name}: {title}", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
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
    fig, axes = plt.subplots(1, len(panels), figsize=(2.4 * len(panels), 2.75), squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.02, top=0.82, wspace=0.06)
    scatters, names = [], list(panels)
    for ax, name in zip(axes[0], names):
        scatters.append(ax.scatter([], [], s=4, c=[]))
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
            panels = {"ground truth": forward["truth"].numpy(), **{k: v.numpy() for k, v in forward["predicted"].items()}}
            animate(panels, titles, forward["particle_type"], bounds, out / f"forward_{dataset}.gif",
                    animation.max_frames, animation.fps)
            written.append(f"forward_{dataset}.gif")
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
    return written
