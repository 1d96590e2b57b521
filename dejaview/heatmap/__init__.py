"""Start-position heatmaps: which cells of the start area explain the observed end?

``compute_heatmap(scene)`` runs batched optimisations per cell, deduplicates,
weighs solutions by loss likelihood and basin width, and returns a
``HeatmapResult`` (``.write(dir)``: heatmap.ppm, heatmap.png, heatmap.json,
result.json, trajectory.csv).
"""

from dejaview.heatmap.images import read_ppm, write_png, write_ppm
from dejaview.heatmap.result import HeatmapProgress, HeatmapResult
from dejaview.heatmap.search import cell_boxes, compute_heatmap

__all__ = ["compute_heatmap", "HeatmapResult", "HeatmapProgress", "cell_boxes", "read_ppm",
           "write_ppm", "write_png"]
