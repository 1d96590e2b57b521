// The live loss curve of a running job: loss and best loss per iteration, log scale, on a canvas;
// a note under it for a phase that is no loss curve (the posterior sampler's progress).

export class LossChart {
  constructor(canvas) {
    this.canvas = canvas;
    this.points = []; // {iteration, loss, best}
    this.note = '';
  }

  reset() {
    this.points = [];
    this.note = '';
    this.draw();
  }

  setNote(text) {
    this.note = text;
    this.draw();
  }

  add(iteration, loss, best) {
    if (!Number.isFinite(loss) && !Number.isFinite(best)) return;
    this.points.push({ iteration, loss, best });
    this.draw();
  }

  draw() {
    const c = this.canvas;
    const g = c.getContext('2d');
    const w = c.width;
    const h = c.height;
    g.clearRect(0, 0, w, h);
    g.fillStyle = '#11151c';
    g.fillRect(0, 0, w, h);
    const pts = this.points;
    if (!pts.length) {
      g.fillStyle = '#889';
      g.font = '12px sans-serif';
      g.fillText('loss: no job yet', 8, h / 2);
      return;
    }
    const values = pts.flatMap((p) => [p.loss, p.best]).filter((v) => Number.isFinite(v) && v > 0);
    const lo = Math.log10(Math.min(...values));
    const hi = Math.max(lo + 1e-6, Math.log10(Math.max(...values)));
    const maxIt = Math.max(1, ...pts.map((p) => p.iteration));
    const pad = 26;
    const x = (it) => pad + (w - pad - 6) * (it / maxIt);
    const y = (v) => h - 14 - (h - 22) * ((Math.log10(v) - lo) / (hi - lo));
    const line = (key, colour) => {
      g.strokeStyle = colour;
      g.lineWidth = 1.5;
      g.beginPath();
      let first = true;
      for (const p of pts) {
        if (!(p[key] > 0)) continue;
        if (first) g.moveTo(x(p.iteration), y(p[key]));
        else g.lineTo(x(p.iteration), y(p[key]));
        first = false;
      }
      g.stroke();
    };
    line('loss', '#5b8fd9');
    line('best', '#ff9f40');
    g.fillStyle = '#aab';
    g.font = '10px sans-serif';
    g.fillText(`${(10 ** hi).toPrecision(2)}`, 2, 12);
    g.fillText(`${(10 ** lo).toPrecision(2)}`, 2, h - 16);
    g.fillText(`iteration ${pts[pts.length - 1].iteration}`, w - 80, h - 3);
    if (this.note) g.fillText(this.note, pad + 4, h - 3);
    g.fillStyle = '#5b8fd9';
    g.fillText('loss', w - 62, 12);
    g.fillStyle = '#ff9f40';
    g.fillText('best', w - 34, 12);
  }
}
