"""What a heatmap run reports: its progress and its result (either method of ``compute_heatmap``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch


@dataclass
class HeatmapProgress:
    """What the heatmap's progress callback receives after every iteration of every chunk.

    ``iteration`` counts iterations over the whole run; ``loss`` is the chunk's lowest
    current loss and ``best_loss`` the lowest found so far over all chunks.
    """

    iteration: int
    loss: float
    best_loss: float
    elapsed_s: float
    cells_done: int
    cells_total: int
    chunk: int
    chunks: int
    phase: str = "optimize"  # "optimize" | "robustness"


@dataclass
class HeatmapResult:
    """Outcome of ``compute_heatmap``.

    Attributes:
        scene: the scene.
        lo, hi: (2,) x-y corners of the start area.
        cells: (nx, ny).
        probability: (ny, nx) numpy array, row j from -y up, column i from -x; sums to 1.
        solutions: one dict per kept (deduplicated) solution: cell (i, j), loss, level,
            weight (normalised), initial_state.
        candidates: number of optimisations run.
        best: SolveResult of the best solution overall (its trajectory re-simulated).
        settings: what ran (optimizer, gradient, iterations, sigma, samples, radii, ...).
        seconds: wall time of the whole computation.
    """

    scene: object
    lo: tuple[float, float]
    hi: tuple[float, float]
    cells: tuple[int, int]
    probability: np.ndarray
    solutions: list[dict]
    candidates: int
    best: object
    settings: dict = field(default_factory=dict)
    seconds: float = 0.0

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(i, j) of the cell holding the point (x, y) (clamped to the grid)."""
        nx, ny = self.cells
        i = int(np.clip(np.floor((x - self.lo[0]) / (self.hi[0] - self.lo[0]) * nx), 0, nx - 1))
        j = int(np.clip(np.floor((y - self.lo[1]) / (self.hi[1] - self.lo[1]) * ny), 0, ny - 1))
        return i, j

    def rank_of(self, x: float, y: float) -> int:
        """Rank (0 = most probable) of the cell holding (x, y); ties share the better rank."""
        i, j = self.cell_of(x, y)
        return int((self.probability > self.probability[j, i]).sum())

    def entropy_bits(self) -> float:
        """Entropy (bits) of the cell distribution; uniform is log2(nx * ny)."""
        from dejaview.heatmap.weighting import entropy_bits

        return entropy_bits(torch.as_tensor(self.probability.reshape(-1)))

    def to_json(self) -> dict:
        """``heatmap.json`` (scene-format spec, "Outputs"), plus the settings and solutions."""
        nx, ny = self.cells
        return {
            "min": [float(self.lo[0]), float(self.lo[1])],
            "max": [float(self.hi[0]), float(self.hi[1])],
            "cells": [nx, ny],
            "probability": [[float(v) for v in row] for row in self.probability],
            "entropy_bits": self.entropy_bits(),
            "uniform_entropy_bits": math.log2(nx * ny),
            "candidates": self.candidates,
            "settings": self.settings,
            "seconds": self.seconds,
            "solutions": self.solutions,
        }

    def write(self, out_dir, plot: bool = True, truth=None) -> dict[str, Path]:
        """Write heatmap.ppm, heatmap.json, heatmap.png (``plot``), result.json, iterations.csv and
        trajectory.csv (the best solution) to out_dir, whole or not at all
        (``dejaview.result_set``). ``truth``: optional (x, y) marked in the PNG.

        Raises:
            OutputError: the set could not be written (a full disk...): out_dir keeps what it held.
        """
        from dejaview.inference.result import RESULT_FILES
        from dejaview.result_set import write_result_set

        return write_result_set(out_dir, lambda folder: self.write_files(folder, plot, truth),
                                RESULT_FILES + ("heatmap.json", "heatmap.ppm", "heatmap.png"))

    def write_files(self, out: Path, plot: bool = True, truth=None) -> dict[str, Path]:
        """``write``'s files, written straight into the folder ``out`` (exists)."""
        import json

        from dejaview.heatmap.images import write_png, write_ppm

        paths = self.best.write_files(out)
        result = self.best.to_json()
        result["heatmap"] = {"file": "heatmap.json", "cells": list(self.cells),
                             "entropy_bits": self.entropy_bits(), "candidates": self.candidates,
                             "kept_solutions": len(self.solutions), "seconds": self.seconds}
        paths["result"].write_text(json.dumps(result, indent=2), encoding="utf-8")
        paths["heatmap_json"] = out / "heatmap.json"
        paths["heatmap_json"].write_text(json.dumps(self.to_json(), indent=2), encoding="utf-8")
        paths["heatmap_ppm"] = write_ppm(out / "heatmap.ppm", self.probability)
        if plot:
            start = self.best.initial_state["position"]
            paths["heatmap_png"] = write_png(out / "heatmap.png", self.probability, self.lo, self.hi,
                                             truth=truth, best=(start[0], start[1]),
                                             title=f"{self.scene.name or 'scene'}: where did "
                                                   f"{self.scene.inference.source} start?")
        return paths
