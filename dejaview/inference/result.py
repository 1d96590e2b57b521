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
            ``InferenceProblem``).
        optimization: the raw OptimizationResult.
        initial_state: dict of the best initial state (object-frame position, orientation,
            linear_velocity, angular_velocity) as lists.
        loss: best loss.
        trajectory: the best solution re-simulated (record every step), batch of 1.
        settings: optimizer, gradient, iterations, seed, backend.
        posterior: ``PosteriorSamples`` where samples were drawn (``write``: posterior.csv), else None.
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

    def final_pose(self) -> tuple[list[float], list[float]]:
        """Object-frame position and orientation of the source at the end of the trajectory."""
        return self.problem.final_pose(self.trajectory)

    def matched_pose(self) -> dict:
        """Where the answer meets the observation: the record of the re-simulated trajectory that
        the scene compares with the target (its ``time``, else the best-matching record by the
        scene's loss for ``evaluate="best"``, else the last), the source's object-frame pose
        there and its errors against the target.

        Returns:
            dict with ``time`` (s), ``position``, ``orientation`` (w x y z), ``position_error``
            (m, object-frame origins) and ``angle_error_deg`` (geodesic).
        """
        from dejaview.losses import LOSSES
        from dejaview.losses.trajectory import nearest_record
        from dejaview.sim.rotation import geodesic_angle

        problem, traj = getattr(self.problem, "inner", self.problem), self.trajectory
        target = self.scene.inference.target
        world, source = problem.world, problem.source
        kw = dict(dtype=world.dtype)
        t_pos = torch.tensor(target.position, **kw)
        t_q = torch.tensor(target.orientation, **kw)
        t_q = t_q / t_q.norm()
        with torch.no_grad():
            if target.time is not None:
                k = nearest_record(traj, target.time)
            elif problem.evaluate == "best":
                per_record = LOSSES[problem.loss_kind](world, source, traj.states, t_pos, t_q,
                                                       orientation_weight=problem.orientation_weight,
                                                       points=problem.points)[:, 0]  # (T,)
                k = int(torch.argmin(per_record))
            else:
                k = len(traj.steps) - 1
            origin = world.object_position(traj.states)[k, 0, source]
            q = traj.states.orientation[k, 0, source]
            return {"time": float(traj.steps[k]) * traj.dt, "position": origin.tolist(),
                    "orientation": q.tolist(),
                    "position_error": float(torch.linalg.vector_norm(origin - t_pos)),
                    "angle_error_deg": math.degrees(float(geodesic_angle(q, t_q)))}

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
            **({"matched_pose": self.matched_pose()} if self.problem.backend == "spheres" else {}),
            "target": {"position": list(self.scene.inference.target.position),
                       "orientation": list(self.scene.inference.target.orientation)},
            "loss_kind": self.problem.loss_kind,
            "evaluate": self.problem.evaluate,
            "seed": self.settings.get("seed", 0),
            # the local optimisers' own settings; the default search has none of them
            **{k: self.settings[k] for k in ("multistart", "screened") if k in self.settings},
            "parameters": self.problem.layout.names(),
            "simulation": self.problem.simulation_settings(),
            "stopped_early": self.optimization.stopped,
            **{k: self.settings[k] for k in ("prior", "observation", "model_uncertainty", "search", "posterior")
               if k in self.settings},
            "iterations": [{"iteration": p.iteration, "loss": _num(p.loss), "best_loss": _num(p.best_loss),
                            "duration_s": p.duration_s, "restarted": p.restarted}
                           for p in self.iterations],
        }

    def write(self, out_dir, plot: bool = False) -> dict[str, Path]:
        """Write result.json, iterations.csv, trajectory.csv (and loss.png with ``plot``); with
        posterior samples also posterior.csv and posterior_paths.csv (``posterior_report``)."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
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
        if plot:
            quantity = "-log posterior" if self.settings["optimizer"] == "auto" else "loss"
            paths["plot"] = plot_losses(self.iterations, out / "loss.png", quantity)
        return paths


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
