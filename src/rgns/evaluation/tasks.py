"""The evaluation tasks. Each is built from ``conf/task/*.yaml`` by ``_target_`` and called on
one dataset with the methods to compare: ``task(methods, dataset) -> (results, examples)``.
``results`` goes to ``results.json`` (plain numbers, ``None`` where a value is not finite);
``examples`` are the frames of the first trajectory that the animations show.

- :class:`ForwardRollout`: rollout MSE as GNS defines it, MSE per step, OT and MMD at chosen
  steps, and how many steps each rollout stays stable;  a model trained on every k-th frame
  (``stride``, :attr:`~rgns.evaluation.methods.Method.stride`) is scored on every frame, those
  between its steps filled in (:func:`~rgns.training.rollouts.forward_rollout`), and every method
  also on the frames all of them predict themselves (``rollout_mse_shared``);
- :class:`InverseConsistency`: for each horizon K, K inverse steps back from the true state at
  ``t0 + K`` (inverse MSE against the truth at ``t0``), then K forward steps (consistency MSE
  against the truth at ``t0 + K``); max stable steps;
- :class:`Efficiency`: ms per forward and inverse step (warm, median), and per frame (a step of a
  stride-k model covers k frames), peak memory of a step, parameters.

A task that scores models trained on every k-th frame (``data.stride``) at their stride says so
with ``strided = True``; the others are refused such a model before any work
(:func:`rgns.evaluation.run.evaluate`).

A new task is a class with a ``name`` and that call, a ``conf/task/<name>.yaml`` (``task=all``
lists the files it composes), and its tables in :mod:`rgns.evaluation.report`. A task that also
compares the solver references (:mod:`rgns.evaluation.references`: methods with ``model = None``,
forward-only) says so with ``compares_references = True``; the others never see them.
"""
from __future__ import annotations

import ctypes
import gc
import logging
import math
import multiprocessing
import os
import queue
import statistics
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from rgns.data.contract import KINEMATIC, DatasetError, check_dataset, open_split
from rgns.evaluation.metrics import (density_ratio, divergence_step, mmd, mse_per_step, optimal_transport,
                                    reference_speed, with_last)
from rgns.models import State
from rgns.training.rollouts import strided_inverse_then_forward

log = logging.getLogger(__name__)


@dataclass
class Dataset:
    """The test trajectories one evaluation runs on."""

    name: str
    root: str
    metadata: dict
    trajectories: list[tuple[Tensor, Tensor]]  # (position [T, N, D], particle_type [N]): the first of the split
    start: int  # t0: the first frame a rollout starts from (needs k frames of history before it)
    split: str = "test"
    particle_types: list[int] | None = None  # every type in the split (None: not read)

    @classmethod
    def load(cls, root: str, split: str, trajectories: int | None, history: int, start: int | None,
             device: str = "cpu") -> "Dataset":
        """The first ``trajectories`` of ``split`` (``None``: all), after checking the metadata and
        every trajectory of the split (:func:`~rgns.data.contract.check_dataset`)."""
        if trajectories is not None and trajectories < 1:
            raise ValueError(f"trajectories={trajectories}: evaluate at least 1 trajectory (null: all of the split)")
        if start is not None and start < history:
            raise ValueError(f"start={start}: a rollout needs the {history} frames of history before it (start >= {history})")
        start = history if start is None else start
        contents = check_dataset(root, splits=(split,))
        if not contents.shapes[split]:
            raise DatasetError(f"{Path(root) / f'{split}.h5'}: no trajectories to evaluate")
        with open_split(root, split) as data:
            count = len(data) if trajectories is None else min(trajectories, len(data))
            loaded = [(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device))
                      for p, t in (data[i] for i in range(count))]
        return cls(Path(root).name, str(root), contents.metadata, loaded, start, split, contents.particle_types[split])

    @property
    def bounds(self) -> Tensor:
        return torch.as_tensor(self.metadata["bounds"], dtype=torch.float32)


def finite(value) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def mean_or_none(values) -> float | None:
    values = list(values)
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def stride_of(method) -> int:
    """Frames per step of a method: its model's training stride (solver references: 1)."""
    return getattr(method, "stride", 1)


def shared_stride(methods) -> int:
    """The frames every method predicts itself are the multiples (after t0) of this: the least
    common multiple of their strides (the largest stride when each divides the next)."""
    return math.lcm(*(stride_of(m) for m in methods)) if methods else 1


def progress(total: int, desc: str) -> tqdm:
    return tqdm(total=total, desc=desc, unit="rollout", leave=False, dynamic_ncols=True)


@dataclass
class Divergence:
    """When a rollout counts as broken (see :func:`rgns.evaluation.metrics.divergence_step`):
    a particle ``margin_radii`` connectivity radii outside the box, or a mean kinetic energy
    ``energy_factor`` times that of the true trajectory, or a NaN."""

    margin_radii: float = 2.0
    energy_factor: float = 100.0

    def step(self, positions: Tensor, dataset: Dataset, speed: float) -> int | None:
        radius = float(dataset.metadata["default_connectivity_radius"])
        return divergence_step(positions.cpu(), dataset.bounds, self.margin_radii * radius, speed, self.energy_factor)


def _worker(jobs, run, counter, results) -> None:
    """In a forked copy of the evaluating process: take the next job of ``jobs`` until none is
    left, sending ``(index, result)`` (or ``(index, None, traceback)``), then ``None``."""
    torch.set_num_threads(1)
    try:
        while (j := _take(counter, len(jobs))) is not None:
            try:
                results.put((j, run(jobs[j])))
            except Exception:  # noqa: BLE001 - raised again in the parent, with this traceback
                results.put((j, None, traceback.format_exc()))
                return
    finally:
        results.put(None)


def _take(counter, total: int) -> int | None:
    with counter.get_lock():
        j = counter.value
        counter.value += 1
    return j if j < total else None


def in_parallel(jobs: list, run, here: list[int], workers: int, bar: tqdm | None = None) -> list:
    """``[run(job) for job in jobs]``, computed by ``workers`` processes: this one and forked
    copies of it (``workers - 1``). The jobs listed in ``here`` (indices) run in this process
    only, first (what keeps state here, e.g. the solver references and their timings); the
    others go to whichever process is free, this one included once it is done with its own.
    Results come back pickled, so ``run`` returns plain values and arrays (a tensor would come
    back through shared memory that dies with its worker), never ``None``. Without ``fork``, or
    with ``workers=1``, all run here in order. A job's error is raised here, with the worker's
    traceback, once the workers have finished the jobs they hold."""
    done: list = [None] * len(jobs)

    def record(j: int, result) -> None:
        done[j] = result
        if bar is not None:
            bar.update()

    shared = [j for j in range(len(jobs)) if j not in set(here)]
    workers = min(workers, len(shared) + 1)
    if workers <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        for j in range(len(jobs)):
            record(j, run(jobs[j]))
        return done
    context = multiprocessing.get_context("fork")
    counter, results = context.Value("i", 0), context.Queue()
    shared_jobs = [jobs[j] for j in shared]
    children = [context.Process(target=_worker, args=(shared_jobs, run, counter, results), daemon=True)
                for _ in range(workers - 1)]
    for child in children:
        child.start()
    running, failure = len(children), None

    def stop() -> None:  # no more jobs for anyone
        with counter.get_lock():
            counter.value = len(shared_jobs)

    def receive(block: bool) -> None:
        nonlocal running, failure
        while running:
            try:
                message = results.get(block=block, timeout=5 if block else None)
            except queue.Empty:
                if block and not any(child.is_alive() for child in children):
                    running = 0  # a worker died without a word (killed): "lost" below names its jobs
                if not block or not running:
                    return
                continue
            if message is None:
                running -= 1
            elif len(message) == 3:
                failure = failure or f"forward rollout {shared_jobs[message[0]]} failed in a worker:\n{message[2]}"
                stop()
            else:
                record(shared[message[0]], message[1])

    try:
        for j in here:
            record(j, run(jobs[j]))
            receive(block=False)
        while failure is None and (j := _take(counter, len(shared_jobs))) is not None:
            record(shared[j], run(shared_jobs[j]))
            receive(block=False)
        receive(block=True)
        clean = True
    except BaseException:
        clean = False
        raise
    finally:
        stop()  # after an error here, the workers take no more jobs
        for child in children:  # after one, a worker may wait on a full pipe that nobody reads
            child.join(timeout=60 if clean else 1)
            if child.is_alive():
                child.kill()
    if failure is not None:
        raise RuntimeError(failure)
    lost = [jobs[j] for j in range(len(jobs)) if done[j] is None]
    if lost:
        raise RuntimeError(f"forward rollouts {lost} got no result (a worker process died: out of memory?)")
    return done


class ForwardRollout:
    """Forward rollouts from frame t0 on each test trajectory.

    Args:
        steps: rollout length (the paper: 300) in frames of the data, whatever a method's stride;
            ``None`` rolls out to the end of each trajectory; always capped by the trajectory's length.
        distribution_steps: rollout steps (1-based) at which OT and MMD are measured; steps past a
            rollout's end are skipped, the last step is always added.
        distribution_particles: OT and MMD on at most this many moving particles (the same random
            subset in prediction and truth).
        divergence: :class:`Divergence` settings.
        workers: processes for the rollouts (this one included). Above 1, forked copies of this
            process roll out the networks and baselines, one (method, trajectory) at a time, while
            this one runs the solver references (whose state and timings stay here) and then joins
            them; the results are the same as with 1. Where ``fork`` is unavailable, 1.
    """

    name = "forward"
    compares_references = True
    strided = True

    def __init__(self, steps: int | None = 300, distribution_steps=(1, 10, 100, 300), distribution_particles: int = 1000,
                 divergence: dict | None = None, seed: int = 0, workers: int = 1):
        if steps is not None and steps < 1:
            raise ValueError(f"task.forward.steps={steps}: roll out at least 1 step (null: to the end of each trajectory)")
        if workers < 1:
            raise ValueError(f"workers={workers}: at least 1 process (this one)")
        self.steps, self.distribution_steps = steps, sorted(set(distribution_steps))
        self.distribution_particles, self.seed, self.workers = distribution_particles, seed, workers
        self.divergence = Divergence(**(divergence or {}))

    def lengths(self, dataset: Dataset) -> list[int]:
        cap = [len(p) - 1 - dataset.start for p, _ in dataset.trajectories]
        return [c if self.steps is None else min(self.steps, c) for c in cap]

    def __call__(self, methods, dataset: Dataset) -> tuple[dict, dict]:
        lengths = self.lengths(dataset)
        if min(lengths) < 1:
            raise ValueError(f"{dataset.name}: a test trajectory is too short to roll out from frame {dataset.start}")
        scale = float(dataset.metadata["default_connectivity_radius"])
        shared = shared_stride(methods)
        for method in methods:
            if hasattr(method, "check_start"):
                method.check_start(dataset.start)
        results, examples = {}, {"start": dataset.start, "truth": None, "predicted": {},
                              "particle_type": dataset.trajectories[0][1].cpu()}
        jobs = [(m, i) for m in range(len(methods)) for i in range(len(lengths))]

        def run(job: tuple[int, int]) -> tuple[dict, np.ndarray | None]:
            # one rollout and its metrics; the frames too for the first trajectory (the animations), as an
            # array: a tensor from a worker would come back through shared memory that dies with the worker
            method, i = methods[job[0]], job[1]
            position, particle_type = dataset.trajectories[i]
            predicted = method.forward_rollout(dataset, i, lengths[i])
            truth = position[dataset.start + 1 : dataset.start + 1 + lengths[i]]
            return (self._metrics(predicted, truth, particle_type, dataset, position, scale, shared),
                    predicted.cpu().numpy() if i == 0 else None)

        bar = progress(len(jobs), f"forward rollouts ({dataset.name})")
        here = [j for j, (m, _) in enumerate(jobs) if methods[m].model is None]  # solver references: their state is here
        done = in_parallel(jobs, run, here, self.workers, bar)
        bar.close()
        for m, method in enumerate(methods):
            per_trajectory = [done[j][0] for j, job in enumerate(jobs) if job[0] == m]
            results[method.label] = dict(self._aggregate(per_trajectory), stride=stride_of(method))
            examples["predicted"][method.label] = torch.from_numpy(done[jobs.index((m, 0))][1])
        examples["truth"] = dataset.trajectories[0][0][dataset.start + 1 : dataset.start + 1 + lengths[0]].cpu()
        settings = dict(start=dataset.start, steps=max(lengths), steps_per_trajectory=lengths,
                        trajectories=len(lengths), particles=int(dataset.trajectories[0][0].shape[1]),
                        shared_stride=shared,  # rollout_mse_shared: frames t0 + shared, t0 + 2 shared, ..
                        distribution_particles=self.distribution_particles, mmd_scale=scale,
                        divergence=vars(self.divergence))
        return dict(settings=settings, methods=results), examples

    def _metrics(self, predicted, truth, particle_type, dataset, position, scale, shared: int = 1) -> dict:
        per_step = mse_per_step(predicted, truth)
        on_shared = per_step[shared - 1 :: shared]  # the frames every method predicts itself
        moving = (particle_type != KINEMATIC).nonzero().squeeze(1)
        density_end = density_ratio(predicted[-1, moving], truth[-1, moving], scale)  # at the last step
        generator = torch.Generator().manual_seed(self.seed)
        if len(moving) > self.distribution_particles:
            moving = moving[torch.randperm(len(moving), generator=generator)[: self.distribution_particles].to(moving.device)]
        steps = with_last([s for s in self.distribution_steps if s <= len(predicted)], len(predicted))
        ot_values, mmd_values = {}, {}
        for s in steps:
            x, y = predicted[s - 1, moving], truth[s - 1, moving]
            ok = bool(torch.isfinite(x).all())
            ot_values[s] = optimal_transport(x, y) if ok else None
            mmd_values[s] = mmd(x, y, scale) if ok else None
        diverged = self.divergence.step(predicted, dataset, reference_speed(position, particle_type))
        bounds = dataset.bounds.to(predicted.device)
        outside = torch.maximum(bounds[:, 0] - predicted, predicted - bounds[:, 1]).clamp(min=0).nan_to_num(math.inf)
        return dict(rollout_mse=finite(per_step.mean()), mse_per_step=[finite(v) for v in per_step],
                    rollout_mse_shared=finite(on_shared.mean()) if len(on_shared) else None,
                    max_outside=finite(outside.max() / scale),  # the farthest a particle got out of the box, in radii
                    density_end=density_end, ot=ot_values, mmd=mmd_values, steps=len(predicted),
                    stable_steps=len(predicted) if diverged is None else diverged, diverged=diverged is not None)

    @staticmethod
    def _aggregate(per_trajectory: list[dict]) -> dict:
        longest = max(r["steps"] for r in per_trajectory)
        curve = []
        for s in range(longest):  # mean over the trajectories that reach step s
            values = [r["mse_per_step"][s] for r in per_trajectory if s < r["steps"]]
            curve.append(mean_or_none(values))
        distribution_steps = sorted({s for r in per_trajectory for s in r["ot"]})

        def at(key, s):
            return mean_or_none(r[key][s] for r in per_trajectory if s in r[key])

        stable = min(r["stable_steps"] for r in per_trajectory)
        return dict(
            rollout_mse=mean_or_none(r["rollout_mse"] for r in per_trajectory),
            rollout_mse_per_trajectory=[r["rollout_mse"] for r in per_trajectory],
            # on the frames every method predicts itself (ForwardRollout's settings: shared_stride)
            rollout_mse_shared=mean_or_none(r["rollout_mse_shared"] for r in per_trajectory),
            mse_per_step=curve,
            ot={s: at("ot", s) for s in distribution_steps},
            mmd={s: at("mmd", s) for s in distribution_steps},
            stable_steps=stable,  # the fewest over the trajectories
            stable_steps_per_trajectory=[r["stable_steps"] for r in per_trajectory],
            max_outside=None if any(r["max_outside"] is None for r in per_trajectory)
            else max(r["max_outside"] for r in per_trajectory),  # radii, over all trajectories and steps
            diverged=any(r["diverged"] for r in per_trajectory),
            # the density at the last step, predicted over true (mean over the trajectories)
            density_end=mean_or_none(r["density_end"] for r in per_trajectory),
            density_end_per_trajectory=[r["density_end"] for r in per_trajectory],
        )


class InverseConsistency:
    """Inverse inference and inverse-then-forward consistency for each horizon K.

    Args:
        horizons: the K tried (the paper: 1 to 100); those longer than the trajectories allow
            (``t0 + K`` past the last frame) are dropped with a warning and listed in the results'
            settings (``dropped_horizons``) and the report.
        threshold: a horizon is stable while its consistency MSE stays under this and neither
            the inferred nor the re-simulated trajectory diverges.

    A model trained on every k-th frame (``stride`` k) runs the horizons that are multiples of
    k, K / k steps of k frames each way (:func:`~rgns.training.rollouts.strided_inverse_then_forward`);
    its other horizons hold ``None`` and ``trajectories = 0`` and are passed over by its max
    stable steps.
        table_horizon: the K of the comparison table (the paper: 40); capped by the horizons run.
        divergence: :class:`Divergence` settings.
    """

    name = "inverse"
    strided = True

    def __init__(self, horizons=(1, 2, 5, 10, 20, 40, 60, 80, 100), threshold: float = 1e-3,
                 table_horizon: int = 40, divergence: dict | None = None):
        if not horizons or min(horizons) < 1:
            raise ValueError(f"task.inverse.horizons={list(horizons)}: each K must be at least 1")
        self.horizons, self.threshold, self.table_horizon = sorted(set(horizons)), threshold, table_horizon
        self.divergence = Divergence(**(divergence or {}))

    def __call__(self, methods, dataset: Dataset) -> tuple[dict, dict]:
        start = dataset.start
        frames = max(len(p) for p, _ in dataset.trajectories)
        longest = frames - 1 - start
        horizons = [K for K in self.horizons if K <= longest]
        if not horizons:
            raise ValueError(f"{dataset.name}: trajectories too short for any inverse horizon from frame {start}")
        dropped = {K: f"longer than the {longest} frames after t0 = {start} of the longest {dataset.split} "
                      f"trajectory ({frames} frames)" for K in self.horizons if K > longest}
        if dropped:
            log.warning("%s: inverse horizons K = %s dropped: %s", dataset.name, ", ".join(map(str, dropped)),
                        next(iter(dropped.values())))
        bidirectional = [m for m in methods if m.bidirectional]
        work = sum(K <= len(p) - 1 - start and K % stride_of(m) == 0
                   for m in bidirectional for p, _ in dataset.trajectories for K in horizons)
        bar = progress(work, f"inverse horizons ({dataset.name})")
        results, examples = {}, {"start": start, "horizon": horizons[-1], "truth": None, "inferred": {}, "resimulated": {},
                                "particle_type": dataset.trajectories[0][1].cpu()}
        for method in bidirectional:
            per_horizon, stride = {}, stride_of(method)
            method.check_start(start)
            for K in horizons:
                rows = []
                for i, (position, particle_type) in enumerate(dataset.trajectories):
                    if start + K > len(position) - 1 or K % stride:
                        continue
                    inferred, resimulated = strided_inverse_then_forward(method.model, position, particle_type, start,
                                                                         K, stride)
                    speed = reference_speed(position, particle_type)
                    broken = (self.divergence.step(inferred.flip(0), dataset, speed) is not None
                              or self.divergence.step(resimulated, dataset, speed) is not None)
                    rows.append(dict(inverse_mse=finite((inferred[-1] - position[start]).pow(2).mean()),
                                     consistency_mse=finite((resimulated[-1] - position[start + K]).pow(2).mean()),
                                     diverged=broken))
                    if i == 0 and K == horizons[-1]:
                        examples["truth"] = position[start : start + K + 1].cpu()  # frames t0 .. t0+K
                        examples["inferred"][method.label] = inferred.cpu()  # frames t0+K-1 .. t0
                        examples["resimulated"][method.label] = resimulated.cpu()  # frames t0+1 .. t0+K
                    bar.update()
                per_horizon[K] = dict(
                    inverse_mse=mean_or_none(r["inverse_mse"] for r in rows),
                    consistency_mse=mean_or_none(r["consistency_mse"] for r in rows),
                    diverged=any(r["diverged"] for r in rows), trajectories=len(rows))
                if K % stride:
                    per_horizon[K]["not_run"] = f"not a multiple of the method's stride, {stride} frames a step"
            results[method.label] = dict(horizons=per_horizon, stride=stride, **self._stability(per_horizon))
        bar.close()
        table_horizon = max([K for K in horizons if K <= self.table_horizon] or horizons[:1])
        settings = dict(start=start, horizons=horizons, dropped_horizons=dropped, threshold=self.threshold,
                        table_horizon=table_horizon, history=max((m.model.history for m in bidirectional), default=None),
                        trajectories=len(dataset.trajectories), divergence=vars(self.divergence))
        return dict(settings=settings, methods=results), examples

    def _stability(self, per_horizon: dict) -> dict:
        """Max stable steps: the largest K such that every K' <= K tried stays under the
        threshold without diverging; ``stable_beyond_tested`` when all of them do. Horizons not
        run (``not_run``: not a multiple of a strided model's stride) are passed over."""
        stable = 0
        for K, row in sorted(per_horizon.items()):
            if "not_run" in row:
                continue
            value = row["consistency_mse"]
            if row["diverged"] or value is None or value >= self.threshold:
                return dict(max_stable_steps=stable, stable_beyond_tested=False)
            stable = K
        return dict(max_stable_steps=stable, stable_beyond_tested=True)


def _status_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"{field} not in /proc/self/status")


def _peak_rss_child(fn, connection) -> None:
    """In a forked child: rise of the resident set's high-water mark over one call of ``fn``."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 64 * 1024)  # M_MMAP_THRESHOLD: blocks over 64 KiB are mapped, and unmapped when freed
        libc.malloc_trim(0)  # free heap pages the parent left resident would hide the step's allocations
        fn()  # fault in the library pages a fork does not copy, which would count as memory of the step
        rises = []
        for _ in range(2):  # the smaller of two: garbage collection's timing moves the peak a little
            gc.collect()
            libc.malloc_trim(0)
            base = _status_mb("VmRSS")
            Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
            fn()
            rises.append(_status_mb("VmHWM") - base)
        connection.send(min(rises))
    except Exception as error:  # noqa: BLE001 - reported to the parent, which records None
        connection.send(repr(error))
    finally:
        connection.close()


def peak_memory_mb(fn, device: torch.device) -> float | None:
    """Peak memory one call of ``fn`` needs beyond what is already allocated (weights, data).

    CUDA: ``torch.cuda.max_memory_allocated`` over the call. CPU: the rise of the resident set's
    high-water mark (``VmHWM``, reset through ``/proc/self/clear_refs``) over a call (the smaller
    of two, after a warm-up call), in
    a forked copy of this process with glibc's mmap threshold at 64 KiB and its free heap pages
    released (``malloc_trim``), so that the peak is of live memory, not of the allocator's cache;
    the first call faults in the shared-library pages the child does not inherit.
    ``None`` where neither applies.
    """
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        fn()
        torch.cuda.synchronize(device)
        return (torch.cuda.max_memory_allocated(device) - base) / 2**20
    if not Path("/proc/self/clear_refs").exists() or "fork" not in multiprocessing.get_all_start_methods():
        return None
    receive, send = multiprocessing.Pipe(duplex=False)
    child = multiprocessing.get_context("fork").Process(target=_peak_rss_child, args=(fn, send))
    child.start()
    value = receive.recv()
    child.join()
    return value if isinstance(value, float) else None


def median_ms(fn, repeats: int, device: torch.device) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        begin = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(1e3 * (time.perf_counter() - begin))
    return statistics.median(times)


class Efficiency:
    """Cost of one step on a real test state (the first trajectory at frame t0), radius graph
    included: forward and inverse ms per step (median of ``repeats`` after a warm-up), peak
    memory of a step (see :func:`peak_memory_mb`) plus the weights, and parameters. A solver
    reference reports its own cost instead: ms per frame of its rollout of the first trajectory
    (:meth:`rgns.evaluation.references.SolverReference.cost`). Each row also has ``stride`` and
    ``forward_ms_per_frame``, the ms per step over the frames a step covers (a model trained at
    ``data.stride = k`` steps k frames; the state it is timed on has its velocities over k
    frames); the same as ms per step at stride 1.

    Args:
        repeats: timed repeats per measurement.
        memory: measure the peak memory (a forked process per measurement on the CPU).
    """

    name = "efficiency"
    compares_references = True
    strided = True

    def __init__(self, repeats: int = 5, memory: bool = True):
        self.repeats, self.memory = repeats, memory

    def __call__(self, methods, dataset: Dataset) -> tuple[dict, dict]:
        position, particle_type = dataset.trajectories[0]
        results = {}
        for method in tqdm(methods, desc=f"efficiency ({dataset.name})", leave=False, dynamic_ncols=True):
            model = method.model
            stride = stride_of(method)
            if model is None:  # a solver reference: the ms per frame of its own rollout
                cost = method.cost(dataset)
                results[method.label] = dict(cost, stride=stride, forward_ms_per_frame=cost["forward_ms_per_step"])
                continue
            device = next(iter(model.buffers())).device
            # the state a rollout starts from: a strided model's history is of velocities over its stride
            method.check_start(dataset.start)
            first = dataset.start - stride * model.history
            state = State.from_positions(position[first : dataset.start + 1 : stride], particle_type)
            weights_mb = sum(t.numel() * t.element_size() for t in [*model.parameters(), *model.buffers()]) / 2**20
            directions = {"forward": model.step} | ({"inverse": model.inverse_step} if model.bidirectional else {})
            row = dict(parameters=method.parameters, weights_mb=weights_mb)
            for direction, step in directions.items():
                with torch.no_grad():
                    row[f"{direction}_ms_per_step"] = median_ms(lambda: step(state), self.repeats, device)
                    peak = peak_memory_mb(lambda: step(state), device) if self.memory else None
                row[f"{direction}_step_peak_mb"] = peak
                row[f"{direction}_memory_mb"] = None if peak is None else weights_mb + peak
            # a step of a stride-k model moves the simulation k frames on: its cost per frame of the data
            row.update(stride=stride, forward_ms_per_frame=row["forward_ms_per_step"] / stride)
            results[method.label] = row
        models = [m.model for m in methods if m.model is not None]
        edges = int(models[0].graph(position[dataset.start]).size(1)) if models else 0
        settings = dict(frame=dataset.start, particles=int(position.shape[1]), edges=edges, repeats=self.repeats,
                        device=str(position.device), threads=torch.get_num_threads(),
                        memory_method=("parameters and buffers plus the rise of torch.cuda.max_memory_allocated over one step"
                                       if position.is_cuda else
                                       "parameters and buffers plus the rise of VmHWM over one warm step in a "
                                       "forked process (glibc mmap threshold 64 KiB, free heap trimmed; smaller of two "
                                       "steps; run-to-run spread about 15 %)"))
        return dict(settings=settings, methods=results), {}
