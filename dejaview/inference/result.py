"""``SolveResult``: what ``dejaview.inference.solve.solve`` returns, its ``result.json`` and the
files it writes (result.json, iterations.csv, trajectory.csv, posterior.csv, loss.png)."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch

from dejaview.inference.optimize import OptimizationResult, Progress
from dejaview.sim.integrate import Trajectory


@dataclass
class SolveResult:
    """Outcome of ``solve``.

    Attributes:
        scene: the scene solved.
        problem: the backend's problem (``dejaview.backends``; ``SpheresProblem`` wraps an
            ``SpheresProblem``).
        optimization: the raw OptimizationResult.
        initial_state: dict of the best initial state (object-frame position, orientation,
            linear_velocity, angular_velocity) as lists.
        loss: best loss.
        trajectory: the best solution re-simulated (record every step), batch of 1.
        settings: optimizer, gradient, iterations, seed, backend.
        posterior: ``PosteriorSamples`` where samples were drawn (``write``: posterior.csv), else None:
            torch tensors in the layout's scaled coordinates; ``posterior_arrays``,
            ``posterior_frame`` and ``to_arviz`` give them in physical units.
    """

    scene: object
    problem: object
    optimization: OptimizationResult
    initial_state: dict
    loss: float
    trajectory: Trajectory
    settings: dict = field(default_factory=dict)
    posterior: object = None

    @property
    def iterations(self) -> list[Progress]:
        return self.optimization.history

    def posterior_arrays(self) -> dict:
        """The posterior samples as numpy arrays (N,): each free parameter in physical units under
        ``result.json``'s name (``position.x`` m, ``orientation.rx`` rad, ...), then ``weight``,
        ``run`` and ``log_density`` (``posterior_data.parameter_arrays``).

        Raises:
            ValueError: no samples were drawn (``SolveParams(samples=N)``).
        """
        from dejaview.inference.posterior_data import parameter_arrays

        return parameter_arrays(self._samples(), self.problem.layout)

    def posterior_frame(self):
        """``posterior.csv`` as a pandas DataFrame (its columns and values; the ``analysis`` extra).

        Raises:
            ValueError: no samples were drawn. ImportError: pandas is not installed.
        """
        from dejaview.inference.posterior_data import frame

        return frame(self._samples(), self.problem.layout)

    def to_arviz(self):
        """The posterior samples as an ``arviz.InferenceData``, the sampler's runs as chains
        (``posterior_data.to_inference_data``; ``posterior.nc`` holds the same).

        Raises:
            ValueError: no samples were drawn. ImportError: arviz is not installed.
        """
        from dejaview.inference.posterior_data import to_inference_data

        return to_inference_data(self._samples(), self.problem.layout, self._arviz_attrs())

    def _samples(self):
        if self.posterior is None:
            raise ValueError("no posterior samples: solve with SolveParams(samples=N) or --samples N")
        return self.posterior

    def _arviz_attrs(self) -> dict:
        return {"source": str(self.scene.inference.source), "seed": int(self.settings.get("seed") or 0)}

    def final_pose(self) -> tuple[list[float], list[float]]:
        """Object-frame position and orientation of the source at the end of the trajectory."""
        return self.problem.final_pose(self.trajectory)

    def matched_pose(self) -> dict:
        """Where the answer meets the last observation (``scene.inference.target``): the record of
        the re-simulated trajectory the scene compares with it (its ``time``, else the end for a
        source seen at rest, else the best-matching record by the scene's loss for a moving target
        under ``evaluate="best"``, else the last), the source's object-frame pose there and its
        errors against the target.

        Returns:
            dict with ``time`` (s), ``position``, ``orientation`` (w x y z), ``position_error``
            (m, object-frame origins) and ``angle_error_deg`` (geodesic; None where the target
            observed the position alone).
        """
        from dejaview.losses.targets import record_index

        problem = self.problem
        sightings = list(problem.sightings)
        anchor = sightings[list(problem.targets).index(self.scene.inference.target)]
        if anchor.step is not None:
            k = record_index(self.trajectory.steps, anchor.step)
        else:
            k = self._best_record(anchor.target)
        return self._pose_at(k, anchor.target)

    def observations(self) -> list[dict]:
        """The answer against every observation, as a user would check it: each target with a
        ``time`` against the re-simulated trajectory at that moment, one without against its END
        (where the source lies, or flies on), with, for a moving target under
        ``evaluate="best"``, the best-matching record beside it (``matched``).

        Returns:
            one dict per target (file order): ``time`` (s, the moment compared), ``at_rest``,
            ``position_error`` (m), ``angle_error_deg`` (None without an observed orientation),
            ``position`` and ``orientation`` of the answer there, and ``matched`` where it differs.
        """
        from dejaview.losses.targets import record_index

        problem = self.problem
        out = []
        for s in problem.sightings:
            t = s.target
            k = record_index(self.trajectory.steps, s.step) if t.time is not None else len(self.trajectory.steps) - 1
            row = {"target_time": t.time, "at_rest": s.at_rest, **self._pose_at(k, t)}
            if s.step is None:
                row["matched"] = self._pose_at(self._best_record(t), t)
            out.append(row)
        return out

    def end_error(self) -> dict:
        """The re-simulated END against the last observation (``observations``' row of
        ``scene.inference.target`` where it has no time; else that target at its time)."""
        problem = self.problem
        i = list(problem.targets).index(self.scene.inference.target)
        row = self.observations()[i]
        return {k: row[k] for k in ("time", "position_error", "angle_error_deg")}

    def _best_record(self, target) -> int:
        """Index of the re-simulated record that fits ``target`` best by the scene's loss."""
        from dejaview.losses import LOSSES

        problem, traj = self.problem, self.trajectory
        world = problem.frames
        kind = problem.loss_kind if target.orientation is not None else "position"
        t_pos = torch.tensor(target.position, dtype=world.dtype)
        t_q = torch.tensor(target.orientation if target.orientation is not None else (1.0, 0, 0, 0), dtype=world.dtype)
        with torch.no_grad():
            per_record = LOSSES[kind](world, problem.source, traj.states, t_pos, t_q / t_q.norm(),
                                      orientation_weight=problem.orientation_weight, points=problem.points)[:, 0]
        return int(torch.argmin(per_record))

    def _pose_at(self, k: int, target) -> dict:
        """The source's object-frame pose at record k of the re-simulated trajectory and its errors
        against ``target``."""
        from dejaview.sim.rotation import geodesic_angle

        problem, traj = self.problem, self.trajectory
        world, source = problem.frames, problem.source
        with torch.no_grad():
            origin = world.object_position(traj.states)[k, 0, source]
            q = traj.states.orientation[k, 0, source]
            angle = None
            if target.orientation is not None:
                t_q = torch.tensor(target.orientation, dtype=q.dtype)
                angle = math.degrees(float(geodesic_angle(q, t_q / t_q.norm())))
            err = float(torch.linalg.vector_norm(origin - torch.tensor(target.position, dtype=origin.dtype)))
            return {"time": float(traj.steps[k]) * traj.dt, "position": origin.tolist(), "orientation": q.tolist(),
                    "position_error": err, "angle_error_deg": angle}

    def to_json(self) -> dict:
        """``result.json`` content (scene-format spec, "Outputs")."""
        end_pos, end_q = self.final_pose()
        return {
            "source": self.scene.inference.source,
            "backend": self.settings.get("backend", self.problem.backend),
            "optimizer": self.settings["optimizer"],
            "gradient": self.settings["gradient"],
            "loss": self.loss,
            "initial_state": self.initial_state,
            "final_pose": {"position": end_pos, "orientation": end_q},
            "end_error": self.end_error(),
            "matched_pose": self.matched_pose(),
            "observations": self.observations(),
            "target": _target_json(self.scene.inference.target),
            "targets": [_target_json(t) for t in self.scene.inference.targets],
            **({"rest": self.settings["rest"]} if "rest" in self.settings else {}),
            "warnings": list(self.settings.get("warnings", [])),
            "loss_kind": self.problem.loss_kind,
            "evaluate": self.problem.evaluate,
            "seed": self.settings.get("seed", 0),
            # the local optimisers' own settings; the default search has none of them
            **{k: self.settings[k] for k in ("multistart", "screened") if k in self.settings},
            "parameters": self.problem.layout.names(),
            "simulation": self.problem.simulation_settings(),
            "stopped_early": self.optimization.stopped,
            **{k: self.settings[k] for k in ("prior", "observation", "model_uncertainty", "physics", "search", "amortised", "posterior",
                                             "truth") if k in self.settings},
            "iterations": [{"iteration": p.iteration, "loss": _num(p.loss), "best_loss": _num(p.best_loss),
                            "duration_s": p.duration_s, "restarted": p.restarted}
                           for p in self.iterations],
        }

    def write(self, out_dir, plot: bool = False) -> dict[str, Path]:
        """Write result.json, iterations.csv, trajectory.csv (and loss.png with ``plot``); with
        posterior samples also posterior.csv and posterior_paths.csv (``posterior_report``) and,
        where arviz is installed (the ``analysis`` extra), posterior.nc (``posterior_data``); whole
        or not at all (``dejaview.result_set``).

        Raises:
            OutputError: the set could not be written (a full disk...): out_dir keeps what it held.
        """
        from dejaview.result_set import write_result_set

        return write_result_set(out_dir, lambda folder: self.write_files(folder, plot), RESULT_FILES)

    def write_files(self, out: Path, plot: bool = False) -> dict[str, Path]:
        """``write``'s files, written straight into the folder ``out`` (exists)."""
        paths = {"result": out / "result.json", "iterations": out / "iterations.csv",
                 "trajectory": out / "trajectory.csv"}
        paths["result"].write_text(json.dumps(self.to_json(), indent=2), encoding="utf-8")
        with open(paths["iterations"], "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh, lineterminator="\n")
            writer.writerow(["iteration", "loss", "best_loss", "duration_s", "restarted"])
            for p in self.iterations:
                writer.writerow([p.iteration, f"{p.loss:.9g}", f"{p.best_loss:.9g}",
                                 f"{p.duration_s:.6f}", int(p.restarted)])
        self.problem.write_trajectory(paths["trajectory"], self.trajectory)
        if self.posterior is not None:
            from dejaview.inference.posterior_report import write_csv, write_paths

            paths["posterior"] = write_csv(out / "posterior.csv", self.posterior, self.problem.layout)
            paths["posterior_paths"] = write_paths(out / "posterior_paths.csv", self.problem, self.posterior,
                                                   seed=int(self.settings.get("seed") or 0))
            from dejaview.inference.posterior_data import write_netcdf

            nc = write_netcdf(out / "posterior.nc", self.posterior, self.problem.layout, self._arviz_attrs())
            if nc is not None:  # the analysis extra (arviz) is installed
                paths["posterior_nc"] = nc
        if plot:
            quantity = "-log posterior" if self.settings["optimizer"] == "auto" else "loss"
            paths["plot"] = plot_losses(self.iterations, out / "loss.png", quantity)
        return paths


RESULT_FILES = ("result.json", "iterations.csv", "trajectory.csv", "posterior.csv", "posterior_paths.csv",
                "posterior.nc", "loss.png")
"""Every file a solve's result set may hold."""


def _target_json(t) -> dict:
    """A target as result.json lists it (what was given, and whether it was seen at rest)."""
    out = {"position": list(t.position),
           "orientation": None if t.orientation is None else list(t.orientation)}
    for name in ("linear_velocity", "angular_velocity", "time", "moving"):
        if getattr(t, name) is not None:
            v = getattr(t, name)
            out[name] = list(v) if isinstance(v, tuple) else v
    out["at_rest"] = t.at_rest
    return out


def _num(v: float):
    return v if math.isfinite(v) else None


def plot_losses(history: list[Progress], path, quantity: str = "loss") -> Path:
    """loss.png: the objective per iteration and the best so far (log scale); ``quantity`` names
    it (``loss``, or ``-log posterior`` for the default search)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    its = [p.iteration for p in history]
    ax.semilogy(its, [max(p.loss, 1e-12) for p in history], lw=1, alpha=0.6, label=quantity)
    ax.semilogy(its, [max(p.best_loss, 1e-12) for p in history], lw=2, label=f"best {quantity}")
    for p in history:
        if p.restarted:
            ax.axvline(p.iteration, color="grey", lw=0.5, ls=":")
    ax.set_xlabel("iteration")
    ax.set_ylabel(quantity)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
