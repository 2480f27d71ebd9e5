"""``report.md``: the paper's tables (rollout MSE per dataset and method, efficiency, inverse
comparison) plus consistency against K, built from exactly what ``results.json`` holds.
Each number is written with :func:`number` (4 significant digits in the unit its row or column
names), so a reader or a test can check it against the JSON. The solver references (the dataset's
own solver re-run, :mod:`rgns.evaluation.references`) sit in the same tables as yardsticks: they
are never the bold "best"."""
from __future__ import annotations

GAP = "—"  # not measured / not applicable / not finite


def number(value, scale: float = 1.0, digits: int = 4) -> str:
    return GAP if value is None else f"{value * scale:.{digits}g}"


def steps_cell(steps: int | None, beyond: bool) -> str:
    """``≥ 100`` when stable over every step tried, ``40`` when it failed after 40."""
    return GAP if steps is None else (f"≥ {steps}" if beyond else f"{steps}")


def table(header: list[str], rows: list[list[str]], best_lowest: set[int] = frozenset(),
          yardsticks: set[str] = frozenset()) -> str:
    """A markdown table; in the rows listed in ``best_lowest``, the lowest number is bold, among
    the columns whose header is not in ``yardsticks``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for i, row in enumerate(rows):
        if i in best_lowest:
            values = [float(c) if c != GAP and h not in yardsticks else float("inf") for h, c in zip(header[1:], row[1:])]
            if len(values) > 1 and min(values) < float("inf"):
                j = values.index(min(values)) + 1
                row = row[:j] + [f"**{row[j]}**"] + row[j + 1 :]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def references(results: dict) -> set[str]:
    """Labels of the solver references."""
    return {label for label, info in results["methods"].items() if info.get("source") == "reference"}


def references_text(name: str, d: dict) -> list[str]:
    """What the solver references on a dataset are, or the sentence that says why there are none."""
    section = d.get("references")
    if not section:
        return []
    if not section["methods"]:
        return [f"{name}: {section['note']}", ""]
    return [f"Solver references on {name}, run from frame 0 and compared on the same frames (forward only):", "",
            *(f"- {label}: {info['description']}" for label, info in section["methods"].items()),
            *([f"- {section['note']}"] if section["note"] else []), ""]


def _labels(results: dict, section: str) -> list[str]:
    labels = {}
    for data in results["datasets"].values():
        labels.update(dict.fromkeys(data.get(section, {}).get("methods", {})))
    return list(labels)


def forward_tables(results: dict) -> list[str]:
    labels = _labels(results, "forward")
    datasets = {name: d for name, d in results["datasets"].items() if "forward" in d}
    if not datasets:
        return []
    measured = "; ".join(
        f"{name}: {d['forward']['settings']['trajectories']} {d['split']} trajectories, rollouts of "
        f"{d['forward']['settings']['steps']} steps from frame {d['forward']['settings']['start']} "
        f"(capped by each trajectory's length)" for name, d in datasets.items())
    yardsticks = references(results)
    out = ["## Rollout MSE (1e-3) in the forward process", "",
           f"Measured on {measured}. Rollout MSE as GNS defines it: mean over steps x particles x dims of the "
           "squared position error (kinematic particles included, at zero error)."
           + (" Bold: the best learned or training-free method (solver references are yardsticks)." if yardsticks else ""),
           "", table(["Dataset / Methods", *labels],
                     [[name, *(number(d["forward"]["methods"].get(m, {}).get("rollout_mse"), 1e3) for m in labels)]
                      for name, d in datasets.items()], best_lowest=set(range(len(datasets))), yardsticks=yardsticks), "",
           *(line for name, d in datasets.items() for line in references_text(name, d)),
           "Stable steps of the forward rollouts (the fewest over the trajectories; ≥ n: no divergence in the "
           "n steps rolled out):", "",
           table(["Dataset / Methods", *labels],
                 [[name, *(steps_cell(d["forward"]["methods"][m]["stable_steps"], not d["forward"]["methods"][m]["diverged"])
                           if m in d["forward"]["methods"] else GAP for m in labels)] for name, d in datasets.items()])]
    for name, d in datasets.items():
        forward = d["forward"]
        steps = sorted({s for row in forward["methods"].values() for s in row["ot"]}, key=int)
        header = ["Method", "Rollout MSE (1e-3)", *(f"OT (1e-3), step {s}" for s in steps),
                  *(f"MMD (1e-2), step {s}" for s in steps), "Stable steps", "Farthest outside the box (radii)",
                  "Density at the end (predicted / true)"]
        rows = [[label, number(row["rollout_mse"], 1e3), *(number(row["ot"].get(s), 1e3) for s in steps),
                 *(number(row["mmd"].get(s), 1e2) for s in steps), steps_cell(row["stable_steps"], not row["diverged"]),
                 "—" if row.get("max_outside") is None else f"{row['max_outside']:.2f}",
                 "—" if row.get("density_end") is None else f"{row['density_end']:.2f}"]
                for label, row in forward["methods"].items()]
        s = forward["settings"]
        out += ["", f"### Forward rollouts on {name}", "",
                f"Measured on {s['trajectories']} {d['split']} trajectories ({s['particles']} particles), "
                f"{s['steps']} steps from frame {s['start']}. OT: squared 2-Wasserstein distance; MMD: squared MMD with "
                f"Gaussian kernels at {s['mmd_scale']:g} x (0.5, 1, 2); both on at most {s['distribution_particles']} "
                "moving particles, averaged over the trajectories. Density at the end: the mean number of "
                "neighbours within the connectivity radius at the last step, predicted over true (1: the water "
                "keeps the solver's density; above 1: compressed; below: spread thinner).", "", table(header, rows)]
    return out


def seed_tables(results: dict) -> list[str]:
    """Runs that differ only by their seed: mean, spread and range of their headline numbers."""
    out = []
    for name, d in results["datasets"].items():
        groups = d.get("over_seeds") or {}
        if not groups:
            continue
        summary = d.get("summary", {})
        yardsticks = {label: row["rollout_mse"] for label, row in summary.items()
                      if label in ("Const. velocity", "Ballistic + walls") and row.get("rollout_mse")}
        header = ["Runs", "Rollout MSE (1e-3): mean ± std", "min – max", *(f"mean / {y}" for y in yardsticks),
                  "Consistency MSE (1e-3): mean ± std"]
        rows = []
        for group, entry in groups.items():
            mse, consistency = entry.get("rollout_mse"), entry.get("consistency_mse")
            rows.append([group,
                         GAP if mse is None else f"{1e3 * mse['mean']:.3g} ± {1e3 * mse['std']:.2g}",
                         GAP if mse is None else f"{1e3 * mse['min']:.3g} – {1e3 * mse['max']:.3g}",
                         *(GAP if mse is None else f"{mse['mean'] / value:.3g}" for value in yardsticks.values()),
                         GAP if consistency is None else f"{1e3 * consistency['mean']:.3g} ± {1e3 * consistency['std']:.2g}"])
        out += ["", f"### Over seeds on {name}", "",
                "Runs whose training differed only by `seed`: the mean and sample standard deviation of their "
                "numbers above.", "", table(header, rows)]
    return out


def efficiency_tables(results: dict) -> list[str]:
    out = []
    for name, d in results["datasets"].items():
        if "efficiency" not in d:
            continue
        cost, s = d["efficiency"]["methods"], d["efficiency"]["settings"]
        labels, solvers = list(cost), [m for m in cost if m in references(results)]
        timing = ""
        if solvers:
            taichi = d["references"]["methods"][solvers[0]]["taichi"]
            timing = (f" Solver references ({', '.join(solvers)}): ms per frame of the solver's own rollout of that "
                      f"trajectory from frame 0 ({cost[solvers[0]]['frames']} frames; wall time / frames, Taichi on "
                      f"{taichi.get('arch')} with {taichi.get('num_threads')} thread(s), JIT warm-up excluded), no "
                      "radius graph, no parameters; memory not measured. Bold: the best learned or training-free method.")
        rows = [
            ["Parameter Count (M)", *(number(cost[m]["parameters"], 1e-6) for m in labels)],
            ["Forward Inference Time (ms/step)", *(number(cost[m]["forward_ms_per_step"]) for m in labels)],
            ["Inverse Inference Time (ms/step)", *(number(cost[m].get("inverse_ms_per_step")) for m in labels)],
            ["Inference Memory (MB)", *(number(cost[m]["forward_memory_mb"]) for m in labels)],
            ["Inverse Inference Memory (MB)", *(number(cost[m].get("inverse_memory_mb")) for m in labels)],
        ]
        if any((cost[m].get("stride") or 1) > 1 for m in labels):  # a step over several frames: per frame too
            rows.insert(2, ["Stride (frames per step)", *(str(cost[m].get("stride") or 1) for m in labels)])
            rows.insert(3, ["Forward Inference Time (ms/frame)",
                            *(number(cost[m].get("forward_ms_per_frame", cost[m]["forward_ms_per_step"])) for m in labels)])
        out += ["", f"## Efficiency comparison on {name}", "",
                f"Measured on the first {d['split']} trajectory at frame {s['frame']}: {s['particles']} particles, "
                f"{s['edges']} edges; one step with its radius graph, median of {s['repeats']} warm repeats on "
                f"{s['device']} with {s['threads']} thread(s). Memory: {s['memory_method']}.{timing}", "",
                table(["Metrics / Methods", *labels], rows, yardsticks=set(solvers),
                      best_lowest={i for i, row in enumerate(rows) if row[0] not in ("Parameter Count (M)",
                                                                                       "Stride (frames per step)")})]
    return out


def dropped_horizons(settings: dict) -> list[str]:
    """A line naming the horizons asked for that did not fit the trajectories, if any."""
    dropped = settings.get("dropped_horizons") or {}
    return ["", f"Not run: K = {', '.join(map(str, dropped))}, {next(iter(dropped.values()))}."] if dropped else []


def inverse_tables(results: dict) -> list[str]:
    out = []
    for name, d in results["datasets"].items():
        if "inverse" not in d:
            continue
        inverse, s, summary = d["inverse"]["methods"], d["inverse"]["settings"], d["summary"]
        labels, K = list(inverse), s["table_horizon"]
        rows = [
            ["Consistency MSE (1e-3)", *(number(summary[m]["consistency_mse"], 1e3) for m in labels)],
            ["Inverse MSE (1e-3)", *(number(summary[m]["inverse_mse"], 1e3) for m in labels)],
            [f"Inference Time, {K} inverse steps (s)", *(number(summary[m].get("inverse_seconds")) for m in labels)],
            ["Parameter Counts (M)", *(number(summary[m].get("parameters"), 1e-6) for m in labels)],
            ["Max Stable Steps", *(steps_cell(summary[m]["max_stable_steps"], summary[m]["stable_beyond_tested"])
                                   for m in labels)],
        ]
        horizons = [str(k) for k in s["horizons"]]
        by_k = [[k, *(number(inverse[m]["horizons"][k]["consistency_mse"], 1e3) for m in labels),
                 *(number(inverse[m]["horizons"][k]["inverse_mse"], 1e3) for m in labels)] for k in horizons]
        out += ["", f"## Inverse inference comparison on {name} (inverse step = {K})", "",
                f"Measured on {s['trajectories']} {d['split']} trajectories: from the true state at frame "
                f"{s['start']} + K, K inverse steps back (inverse MSE against the truth at frame {s['start']}), then K "
                f"forward steps from the inferred state (consistency MSE against the truth at frame {s['start']} + K). "
                f"Max stable steps: the largest K tried ({', '.join(horizons)}) up to which the consistency MSE stays "
                f"under {s['threshold']:g} without divergence (≥: every K tried). Inference time: K x the inverse "
                f"ms/step of the efficiency table. For K ≤ k = {s['history']}, frame {s['start']} is in the given "
                "state's velocity history, so its inverse MSE is exactly 0. Forward-only methods are not listed.",
                *dropped_horizons(s), "",
                table(["Methods", *labels], rows, best_lowest={0, 1, 2}), "",
                f"### Consistency and inverse MSE (1e-3) against the inverse steps K on {name}", "",
                table(["K", *(f"Consistency {m}" for m in labels), *(f"Inverse {m}" for m in labels)], by_k)]
    return out


def optimisation_tables(results: dict) -> list[str]:
    """task=inverse_optimisation: feed-forward against optimisation, per K, and long-rollout stability."""
    out = []
    for name, d in results["datasets"].items():
        if "inverse_optimisation" not in d:
            continue
        section, s = d["inverse_optimisation"], d["inverse_optimisation"]["settings"]
        methods, K = section["methods"], str(s["table_horizon"])
        labels = list(methods)
        rows = [
            [f"Consistency MSE (1e-3), K = {K}", *(number(methods[m]["horizons"].get(K, {}).get("consistency_mse"), 1e3)
                                                  for m in labels)],
            [f"Inference Time, K = {K} (s)", *(number(methods[m]["horizons"].get(K, {}).get("seconds")) for m in labels)],
            ["Max Stable Steps", *(steps_cell(methods[m]["max_stable_steps"], methods[m]["stable_beyond_tested"])
                                   for m in labels)],
        ]
        by_k = [[k, *(number(methods[m]["horizons"].get(k, {}).get("consistency_mse"), 1e3) for m in labels),
                 *(", ".join(methods[m]["horizons"].get(k, {}).get("statuses") or [GAP]) for m in labels)]
                for k in (str(h) for h in s["horizons"])]
        ratios = [[pair, number(ratio)] for pair, ratio in section["time_ratio_at_table_horizon"].items()]
        stability = [[m, str(v["forward"]["stable_steps"]), str(v["inverse"]["stable_steps"])]
                     for m, v in section.get("stability", {}).items()]
        out += ["", f"## Feed-forward against optimisation on {name}", "",
                f"{s['trajectories']} trajectory, {s['particles']} particles, from frame {s['start']}. Optimisers stop by "
                f"one rule for all: {s['rule']}. Consistency: K forward frames of each method's own forward simulator "
                f"from the initial state it found, against the truth at frame {s['start']} + K; stable while under "
                f"{s['threshold']:g} and not failed.", *dropped_horizons(s), "",
                table(["Methods", *labels], rows, best_lowest={0, 1}), "",
                table(["K", *(f"Consistency (1e-3) {m}" for m in labels), *(f"Status {m}" for m in labels)], by_k), "",
                f"Time ratios at K = {K} (optimisation / feed-forward, one run):", "",
                table(["Pair", "Ratio"], ratios)]
        if stability:
            out += ["", "Long rollouts: steps before divergence (NaN, leaving the box, kinetic energy blow-up):", "",
                    table(["Method", "Forward stable steps", "Inverse stable steps"], stability)]
    return out


def _percent(value) -> str:
    return GAP if value is None else f"{100 * value:.1f}"


def goal_tables(results: dict) -> list[str]:
    """task=goal: per K, how closely each method's initial state reproduces the target, by the
    model and by the dataset's own solver, and how plausible that initial state is."""
    out = []
    for name, d in results["datasets"].items():
        if "goal" not in d:
            continue
        for goal in (d["goal"].get("targets") or {"": d["goal"]}).values():  # goal.text=[L,N]: a section each
            out += _goal_section(name, goal)
    return out


def _goal_section(name: str, goal: dict) -> list[str]:
    """One target's tables and figures (see :func:`goal_tables`)."""
    out = []
    shape = goal["goal"]["text"] or goal["goal"]["mask"] or goal["goal"]["points"]
    physics = goal["physics"]
    out += ["", f"## Goal-conditioned shaping on {name}: {shape!r}", "",
            f"Target: {goal['particles']} particles at spacing {goal['spacing']:g}, placed {goal['goal']['place']!r} "
            f"(lift {goal['goal']['lift']:g} m), velocity {goal['velocity']} m/s at frame K ({goal['velocity_history']}). "
            "Per K: each method's initial state run K frames by its own model (for an optimiser: its simulator) "
            f"and by the dataset's solver ({physics['solver'] or 'none'}), the final frame against the target."]
    if physics["note"]:
        out += ["", physics["note"]]
    for K, at in goal["horizons"].items():
        methods = at["methods"]
        rows, checks = [], []
        for m, row in methods.items():
            model, solver, check = row["model"] or {}, row.get("solver") or {}, row["plausibility"]
            rows.append([m, number(model.get("chamfer"), 1e5), number(solver.get("chamfer"), 1e5),
                         number(model.get("ot"), 1e3), number(solver.get("ot"), 1e3), number(row["seconds"]),
                         row["status"] + (f" (solver: {solver['error']})" if solver.get("error") else "")])
            checks.append([m, _percent(check.get("inside_box")), _percent(check.get("overlapping")),
                           _percent(check.get("isolated")), number(check.get("max_speed")),
                           ", ".join(number(v, digits=3) for v in check.get("mean_velocity") or []) or GAP,
                           ", ".join(number(v, digits=3) for v in row["centre_shift"]),
                           _percent(solver.get("clamped")), "; ".join(check["flags"]) or "none"])
        thresholds = physics["thresholds"]
        out += ["", f"### K = {K}", "",
                table(["Method", "Chamfer by model (1e-5)", "Chamfer by solver (1e-5)", "OT by model (1e-3)",
                       "OT by solver (1e-3)", "Time (s)", "Status"], rows), "",
                f"Plausibility of the initial states at K = {K} (training data's max speed: "
                f"{number(physics['train_max_speed'])} m/s):", "",
                table(["Method", "Inside box (%)", f"Overlapping, NN < {thresholds['overlap']:g} h (%)",
                       f"Isolated, NN > {thresholds['isolated']:g} h (%)", "Max speed (m/s)", "Mean velocity (m/s)",
                       "Centre shift from the target (m)", "Clamped (%)", "Flags"],
                      checks)]
    out += ["", *(f"![goal {f}](goal_{name}/{f})" for f in goal["files"] if not f.endswith(".json"))]
    return out


def generalise_tables(results: dict) -> list[str]:
    """task=generalise: per dataset, each method on each condition: rollout MSE, stable steps and
    what broke it first (over the condition's trajectories), and what each condition changed;
    then the same backwards in time (:func:`generalise_inverse_table`) and the break pictures."""
    out = []
    for name, d in results["datasets"].items():
        section = d.get("generalise")
        if not section:
            continue
        s = section["settings"]
        out += ["", f"## Where methods fail on {name}", "",
                f"Each condition generated anew with the dataset's solver ({s['trajectories']} test "
                f"trajector{'y' if s['trajectories'] == 1 else 'ies'}, seed "
                f"{s['seed']}), every method rolled out {s['steps']} steps from frame {s['start']} without retraining "
                "(trained models told the condition's box). Cells: rollout MSE (1e-3) / stable steps (the fewest "
                "over the trajectories), and the first break's cause. Breaks: a NaN; a particle "
                f"{s['rule']['margin_radii']:g} radii out of the box; kinetic energy {s['rule']['energy_factor']:g}x the "
                f"truth's greatest (exploded); a cell of side R holding {s['rule']['compression']:g}x the truth's most "
                f"(compressed); under {s['rule']['stall_fraction']:g}x the truth's mean speed over {s['rule']['window']} "
                "steps while it moves (stalled).", ""]
        if section.get("note"):
            out += [section["note"], ""]
        conditions = section["conditions"]
        ran = [c for c, r in conditions.items() if "methods" in r]
        backwards = [c for c, r in conditions.items() if "inverse" in r]
        out += [f"- {c}: {r.get('description') or r.get('skipped')}"
                + (f" ({span(r['particles'])} particles)" if r.get("particles") else "")
                + ("" if c in ran else " (backwards only)" if c in backwards else " (not run)")
                for c, r in conditions.items()]
        labels = list(dict.fromkeys(label for c in ran for label in conditions[c]["methods"]))
        rows = []
        for label in labels:
            cells = [label]
            for c in ran:
                row = conditions[c]["methods"].get(label)
                cells.append(GAP if row is None else _break_cell(row))
            rows.append(cells)
        if ran:
            out += ["", table(["Method", *ran], rows)]
        out += generalise_inverse_table(name, s, {c: conditions[c]["inverse"] for c in backwards}, labels)
        pictures = [(c, direction, r["break_picture"]) for c in conditions
                    for direction, r in (("forward", conditions[c]), ("inverse", conditions[c].get("inverse") or {}))
                    if r.get("break_picture")]
        if pictures:
            out += ["", *(f"![{name}, {c}, {direction}: each method at its first break, beside the truth]({picture})"
                          for c, direction, picture in pictures)]
    return out


def _break_cell(row: dict) -> str:
    """``rollout MSE (1e-3) / stable steps`` and the first break, ``(cause at step)``."""
    broke = row["first_break"]
    return (f"{number(row['rollout_mse'], 1e3)} / {row['stable_steps']}"
            + (f" ({broke['cause']} at {broke['step']})" if broke else ""))


def generalise_inverse_table(name: str, settings: dict, inverse: dict, order=()) -> list[str]:
    """task=generalise backwards in time: per condition rolled back, each method with an inverse
    (cells as forward), and those without one, named so; rows in ``order`` (the forward table's),
    then any others."""
    if not inverse:
        return []
    frames = sorted({f for r in inverse.values() for f in r["from_frames"]})
    present = [label for r in inverse.values() for label in [*r["methods"], *r["without_inverse"]]]
    labels = list(dict.fromkeys([*(label for label in order if label in present), *present]))
    rows = []
    for label in labels:
        cells = [label]
        for r in inverse.values():
            row = r["methods"].get(label)
            missing = "no inverse" if label in r["without_inverse"] else GAP
            cells.append(missing if row is None else _break_cell(row))
        rows.append(cells)
    without = {label: why for r in inverse.values() for label, why in r["without_inverse"].items()}
    return ["", f"### Backwards in time on {name}", "",
            f"Every method with an inverse rolled back {settings['steps']} steps (fewer where a trajectory is shorter) "
            f"from the last frame of each trajectory (frame {span(frames)}), the truth run backwards as the "
            "reference, "
            "its breaks named by the same rules: speeds are the distances between consecutive frames either way, so "
            "exploded is a kinetic energy far above the true past's greatest and stalled an inferred past at rest "
            "while the true past moves. Cells as above; step s is frame (last - 1 - s).", "",
            table(["Method", *inverse], rows), "",
            *(f"- {label}: no inverse ({why})" for label, why in without.items())]


def span(values: list[int]) -> str:
    """``low-high`` of whole numbers, with thousands separators (``1,053-1,287``), or one number."""
    low, high = min(values), max(values)
    return f"{low:,}" if low == high else f"{low:,}-{high:,}"


def not_evaluated(results: dict) -> list[str]:
    """A section naming the runs and checkpoints asked for but left out, and why, if any."""
    left_out = results.get("not_evaluated") or []
    return ["## Not evaluated", "", "Asked for, but left out of this evaluation (`not_evaluated` in results.json):",
            "", *(f"- {item}" for item in left_out), ""] if left_out else []


def warnings_section(results: dict) -> list[str]:
    """A section naming checkpoints scored on data other than their own, if any."""
    warnings = results.get("warnings") or []
    return ["## Warnings", "", "Scored all the same, but read the numbers with this in mind (`warnings` in "
            "results.json):", "", *(f"- {item}" for item in warnings), ""] if warnings else []


def render(results: dict, charts: list[str]) -> str:
    methods = results["methods"]
    sources = [f"- {label}: `{info['source']}`" + (f" (step {info['global_step']})" if info.get("global_step") else "") for label, info in methods.items()]
    environment = results["environment"]
    lines = ["# rgns evaluation", "",
             f"Reproduce with: `{results['command']}`", "",
             f"Run {results['date']} on {environment['device']} ({environment['threads']} thread(s)), "
             f"torch {environment['torch']}. Methods:", "", *sources, "", *warnings_section(results), *not_evaluated(results),
             *forward_tables(results), *seed_tables(results), *efficiency_tables(results), *inverse_tables(results),
             *optimisation_tables(results), *goal_tables(results), *generalise_tables(results), "", "## Charts", ""]
    lines += [f"![{_title(c)}]({c})" for c in charts]
    return "\n".join(lines) + "\n"


def _title(name: str) -> str:
    return name.rsplit(".", 1)[0].replace("_", " ")
