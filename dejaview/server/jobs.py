"""What a worker does with one job: run simulate / solve / heatmap / train, write the artefacts.

``run_job`` is the same in a worker thread and in a worker process: it gets
the job's spec (kind, scene text, overrides), a folder to write into, a
function to report progress through and a ``StopCheck`` to poll, and returns
the job's summary and the names of the files it wrote. The files appear
atomically (``dejaview.result_set``: written aside, renamed into place), so a
job run again after a crash simply writes the same files again, and a full disk
fails the job (``disk_full``) without a half-written set. Torch and the
simulator are imported here, inside the worker, never by the web process's
event loop.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

from dejaview.server.errors import ServiceError, write_error


class JobStopped(Exception):
    """The job was stopped (cancelled, over its time limit, or its server went away)."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(reason)


class StopCheck:
    """``should_stop`` for the library: True once the job is cancelled, over its time limit,
    or the process that started this worker is gone. ``reason`` says which."""

    def __init__(self, cancelled, timeout_s: float | None = None, parent_pid: int | None = None):
        self.cancelled = cancelled  # callable -> bool
        self.deadline = None if timeout_s is None else time.monotonic() + timeout_s
        self.timeout_s = timeout_s
        self.parent_pid = parent_pid
        self.reason: str | None = None

    def __call__(self) -> bool:
        if self.reason is None:
            if self.cancelled():
                self.reason = "cancelled"
            elif self.deadline is not None and time.monotonic() > self.deadline:
                self.reason = "timeout"
            elif self.parent_pid is not None and os.getppid() != self.parent_pid:
                self.reason = "orphaned"
        return self.reason is not None

    def raise_if_stopped(self) -> None:
        if self():
            raise JobStopped(self.reason)


class Throttle:
    """Pass progress on at most once per ``interval`` seconds (the first and the last always)."""

    def __init__(self, emit, interval: float):
        self.emit = emit
        self.interval = interval
        self.last = -math.inf

    def __call__(self, data: dict, last: bool = False) -> None:
        now = time.monotonic()
        if last or now - self.last >= self.interval:
            self.last = now
            self.emit(data)


def _finite(v):
    return v if isinstance(v, (int, float)) and math.isfinite(v) else None


def run_job(spec: dict, out_dir: Path, emit, stop: StopCheck, progress_interval: float = 0.25,
            memory_limit: int | None = None, models_dir: str | None = None) -> dict:
    """Run one job and write its artefacts into ``out_dir``.

    Args:
        spec: ``{"kind", "text", "base_dir", "root", "filename", "overrides"}`` (``root``: the scene
            root, inside which robots' ``package://`` URIs resolve).
        out_dir: the job's folder (exists).
        emit: called with a progress dict (fields of ``messages.ProgressData``), throttled here.
        stop: polled every iteration / step.
        progress_interval: seconds between progress reports.
        memory_limit: bytes the job may hold (None: ``dejaview.memory.limit()``); a job sized over
            it raises ``ResourceError`` before any work.
        models_dir: where a train job puts its model (``live.model_path``; None: ``models`` beside
            the ``jobs`` folder that holds ``out_dir``).
    Returns:
        ``{"summary": {...}, "artefacts": [file names]}``.
    Raises:
        JobStopped: cancelled, timed out or orphaned.
        DejaViewError: the library's errors (bad scene, simulation or inference problem).
    """
    import torch

    from dejaview.scene.xml import read_scene_string

    torch.set_num_threads(1)  # see dejaview.cli.options.configure_torch: one thread per worker
    scene = read_scene_string(spec["text"], base_dir=spec["base_dir"], filename=spec["filename"],
                              check_files=True, max_bytes=max(len(spec["text"].encode()), 1),
                              root=spec.get("root"))
    overrides = dict(spec.get("overrides") or {}, memory_limit=memory_limit)
    progress = Throttle(emit, progress_interval)
    stop.raise_if_stopped()
    if spec["kind"] == "train":
        from dejaview.server.live import MODELS

        models = Path(models_dir) if models_dir else Path(out_dir).parent.parent / MODELS
        return _train(scene, overrides, Path(out_dir), progress, stop, models)
    runner = {"simulate": _simulate, "solve": _solve, "heatmap": _heatmap}[spec["kind"]]
    # each result set is written whole or not at all (``dejaview.result_set``): a reader, or a
    # run of the same job after a crash, never sees a half-written artefact
    return runner(scene, overrides, Path(out_dir), progress, stop)


def _simulate(scene, overrides, out_dir, progress, stop):
    from dejaview.backends import simulate
    from dejaview.sim.simulate import SimulationStopped

    start = time.perf_counter()

    def step_done(step, total):
        progress({"iteration": step, "total": total, "elapsed_s": time.perf_counter() - start},
                 last=step == total)

    backend = overrides.get("backend") or "spheres"
    limit = {"memory_limit": overrides["memory_limit"]} if backend == "spheres" else {}
    try:
        run = simulate(scene, backend, steps=overrides.get("steps"),
                       record_every=overrides.get("record_every", 1), callback=step_done, should_stop=stop,
                       **limit)
    except SimulationStopped:
        raise JobStopped(stop.reason or "cancelled") from None
    paths = run.write(out_dir)
    summary = {"steps": run.steps, "dt": run.dt, "duration_s": run.steps * run.dt,
               "bodies": list(run.names), "records": len(run.trajectory),
               "elapsed_s": run.elapsed_s, "backend": run.backend}
    return {"summary": summary, "artefacts": sorted(p.name for p in paths.values())}


def _optimiser_progress(total: int, progress):
    def report(p):
        data = {"iteration": p.iteration + 1, "total": total, "loss": _finite(p.loss),
                "best_loss": _finite(p.best_loss), "elapsed_s": p.elapsed_s,
                "evaluations": getattr(p, "evaluations", None)}
        for key in ("cells_done", "cells_total"):
            if getattr(p, key, None) is not None:
                data[key] = int(getattr(p, key))
        if getattr(p, "phase", None) is not None:
            data["phase"] = str(p.phase)
        if getattr(p, "fraction", None) is not None:
            data["fraction"] = float(p.fraction)
        progress(data, last=total is not None and data["iteration"] == total)
    return report


def _solve(scene, overrides, out_dir, progress, stop):
    from dejaview.inference.solve import SolveParams, solve

    total = overrides.get("iterations", scene.inference.iterations)
    params = SolveParams(**{k: overrides[k] for k in ("iterations", "optimizer", "budget", "gradient", "seed",
                                                       "lr", "tolerance", "multistart", "screen",
                                                       "screen_rounds", "samples", "memory_limit")
                            if k in overrides})
    result = solve(scene, params, callback=_optimiser_progress(total, progress), should_stop=stop,
                   backend=overrides.get("backend"))
    if stop.reason is not None:
        raise JobStopped(stop.reason)
    paths = result.write(out_dir)
    end_pos, end_q = result.final_pose()
    summary = {"loss": _finite(result.loss), "iterations": len(result.iterations),
               "initial_state": result.initial_state,
               "final_pose": {"position": end_pos, "orientation": end_q},
               "end_error": result.end_error(), "rest": result.settings.get("rest"),
               "warnings": list(result.settings.get("warnings", [])),
               "optimizer": result.settings.get("optimizer"), "gradient": result.settings.get("gradient")}
    if "posterior" in result.settings:
        post = result.settings["posterior"]
        summary["posterior"] = {"samples": post["samples"], "modes": post["modes"],
                                "intervals": post["intervals"], "agreement": post.get("agreement")}
    return {"summary": summary, "artefacts": sorted(p.name for p in paths.values())}


def _heatmap(scene, overrides, out_dir, progress, stop):
    from dejaview.heatmap import compute_heatmap

    total = None  # iterations run over chunks of cells: cells_done / cells_total tell how far it is
    kwargs = {k: overrides[k] for k in ("cells", "samples", "sigma", "iterations", "optimizer", "gradient",
                                        "seed", "backend", "memory_limit") if k in overrides}
    if "cells" in kwargs:
        kwargs["cells"] = tuple(kwargs["cells"])
    result = compute_heatmap(scene, callback=_optimiser_progress(total, progress), should_stop=stop,
                             **kwargs)
    if stop.reason is not None:
        raise JobStopped(stop.reason)
    paths = result.write(out_dir)
    grid = result.to_json()
    summary = {"cells": grid.get("cells"), "min": grid.get("min"), "max": grid.get("max")}
    result_json = Path(out_dir) / "result.json"
    if result_json.is_file():
        data = json.loads(result_json.read_text(encoding="utf-8"))
        summary["loss"] = _finite(data.get("loss"))
        if "initial_state" in data:
            summary["initial_state"] = data["initial_state"]
    return {"summary": summary, "artefacts": sorted(p.name for p in paths.values())}


TRAIN_OVERRIDES = ("simulations", "seed", "epochs", "patience", "transforms", "hidden", "batch", "lr")


def _train(scene, overrides, out_dir, progress, stop, models_dir: Path):
    """An amortised model of the scene, saved as ``models_dir/<fingerprint>.safetensors`` (where
    live answers look for it) and described in the job's ``result.json``."""
    from dejaview.inference.amortised import train
    from dejaview.inference.params import TrainParams
    from dejaview.result_set import write_result_set
    from dejaview.server.live import MODELS, model_digest, model_path

    start = time.perf_counter()
    params = TrainParams(**{k: tuple(overrides[k]) if k == "hidden" else overrides[k]
                            for k in TRAIN_OVERRIDES if k in overrides},
                         memory_limit=overrides["memory_limit"])  # sized before any simulation
    best = [math.inf]

    def report(d):
        data = {"elapsed_s": time.perf_counter() - start, "phase": d["phase"]}
        if d["phase"] == "simulate":
            data.update(iteration=int(d["done"]), total=int(d["total"]), fraction=min(1.0, d["done"] / d["total"]))
        else:
            best[0] = min(best[0], d["validation_loss"])
            data.update(iteration=int(d["epoch"]), total=int(d["epochs"]), loss=_finite(d["validation_loss"]),
                        best_loss=_finite(best[0]), fraction=d["epoch"] / d["epochs"])
        progress(data)

    model = train(scene, params, callback=report, should_stop=stop)
    if stop.reason is not None:
        raise JobStopped(stop.reason)
    try:
        path = model.save(model_path(models_dir, model.fingerprint))
    except OSError as exc:
        raise write_error(exc) from None
    info = model.info
    summary = {"fingerprint": model.fingerprint, "model": f"{MODELS}/{path.name}", "model_sha256": model_digest(path),
               "scene": info.get("scene"),
               "simulations": info["simulations"], "feasible_share": info["feasible_share"],
               "fit": info["fit"], "seconds": info["seconds"]}
    progress({"iteration": info["fit"]["epochs"], "total": info["fit"]["epochs"], "elapsed_s": time.perf_counter() - start,
              "phase": "fit", "fraction": 1.0}, last=True)

    def write(folder):
        target = folder / "result.json"
        target.write_text(json.dumps({"kind": "train", **summary, "info": info}, indent=2), encoding="utf-8")
        return {"result": target}

    paths = write_result_set(out_dir, write, names=("result.json",))
    return {"summary": summary, "artefacts": sorted(p.name for p in paths.values())}


def worker_error(exc: BaseException) -> ServiceError:
    """The (code, message) a failed job reports for an exception raised by ``run_job``."""
    from dejaview.server.errors import from_library_error

    if isinstance(exc, JobStopped):
        if exc.reason == "timeout":
            return ServiceError("timeout", "the job ran over the server's time limit and was stopped")
        return ServiceError("cancelled", "the job was cancelled")
    return from_library_error(exc)
