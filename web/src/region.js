// Credible regions of the start position: the smallest set of cells of a probability grid that
// holds a given share of its mass (the highest-density region), and such a grid from weighted
// posterior samples (a Gaussian kernel density estimate over the start area's x-y extent).

const MAX_CELLS = 40; // per axis, for a grid from samples

// probability[j][i] (rows from -y up, as heatmap.json) -> {mask[j][i], mass, count}: the most
// probable cells, in order, until their mass reaches `level` of the total.
export function credibleCells(probability, level) {
  const cells = [];
  let total = 0;
  probability.forEach((row, j) => row.forEach((p, i) => {
    const v = Number.isFinite(p) && p > 0 ? p : 0;
    cells.push([v, i, j]);
    total += v;
  }));
  cells.sort((a, b) => b[0] - a[0]);
  const mask = probability.map((row) => row.map(() => false));
  let mass = 0;
  let count = 0;
  for (const [p, i, j] of cells) {
    if (total <= 0 || mass >= level * total) break;
    mask[j][i] = true;
    mass += p;
    count += 1;
  }
  return { mask, mass: total > 0 ? mass / total : 0, count };
}

function weightedStd(values, weights) {
  const mean = values.reduce((s, v, k) => s + v * weights[k], 0);
  return Math.sqrt(values.reduce((s, v, k) => s + weights[k] * (v - mean) ** 2, 0));
}

// samples: [{weight, position: [x, y, z]}]; area: {min, max} (the start area) or null. Returns a
// grid {min, max, cells, probability} of the samples' x-y density, or null without samples. The
// bandwidth is Silverman's rule per axis with the effective sample size, at least a cell; cells
// are about a third of it, at most MAX_CELLS per axis.
export function gridFromSamples(samples, area) {
  const live = samples.filter((s) => s.weight > 0 && s.position.every(Number.isFinite));
  if (!live.length) return null;
  const total = live.reduce((s, x) => s + x.weight, 0);
  const w = live.map((s) => s.weight / total);
  const nEff = 1 / w.reduce((s, v) => s + v * v, 0);
  const xs = live.map((s) => s.position[0]);
  const ys = live.map((s) => s.position[1]);
  const factor = 1.06 * nEff ** -0.2;
  let lo = [Math.min(...xs), Math.min(...ys)];
  let hi = [Math.max(...xs), Math.max(...ys)];
  const spread = Math.max(hi[0] - lo[0], hi[1] - lo[1], 0.01);
  const h = [weightedStd(xs, w), weightedStd(ys, w)].map((sd) => Math.max(factor * sd, spread / MAX_CELLS, 0.002));
  if (area) {
    lo = [area.min[0], area.min[1]];
    hi = [area.max[0], area.max[1]];
  } else {
    lo = lo.map((v, a) => v - 3 * h[a]);
    hi = hi.map((v, a) => v + 3 * h[a]);
  }
  // a flat start area (a line in x or y) gets one cell's width around it
  for (const a of [0, 1]) {
    if (hi[a] - lo[a] < 1e-6) {
      lo[a] -= h[a];
      hi[a] += h[a];
    }
  }
  const cells = [0, 1].map((a) => Math.max(1, Math.min(MAX_CELLS, Math.ceil((3 * (hi[a] - lo[a])) / h[a]))));
  const size = [0, 1].map((a) => (hi[a] - lo[a]) / cells[a]);
  const probability = [];
  for (let j = 0; j < cells[1]; j += 1) {
    const y = lo[1] + (j + 0.5) * size[1];
    const row = [];
    for (let i = 0; i < cells[0]; i += 1) {
      const x = lo[0] + (i + 0.5) * size[0];
      let d = 0;
      for (let k = 0; k < live.length; k += 1) {
        d += w[k] * Math.exp(-0.5 * (((x - xs[k]) / h[0]) ** 2 + ((y - ys[k]) / h[1]) ** 2));
      }
      row.push(d);
    }
    probability.push(row);
  }
  const sum = probability.flat().reduce((s, v) => s + v, 0) || 1;
  return { min: lo, max: hi, cells, probability: probability.map((row) => row.map((v) => v / sum)) };
}
