"""Files DejaView writes and reads: trajectory CSV, heatmaps, result JSON."""
