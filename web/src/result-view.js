// A job's results in the scene and the panel (trajectory, heatmap, posterior samples, summary), and
// the playback of the trajectory; showSetup returns to the set-up poses the gizmos edit.
import { serverFetch } from './connection.js';
import {
  applyPose, heatmapDecal, parsePosterior, parsePosteriorPaths, sampleCloud, samplePaths, summarizeResult,
  trajectorySpline,
} from './results.js';
import { clearPosterior } from './posterior-view.js';
import { highlightObservations, placeFromModel, placeObservations, poseRobots } from './scene-view.js';
import { updateSelectionText } from './selection.js';
import { gizmo, world } from './stage.js';
import { $, app, notify } from './state.js';

export function clearResults() {
  for (const key of ['path', 'heatmap', 'samples', 'samplePaths']) {
    if (app[key]) app[key].removeFromParent();
    app[key] = null;
  }
  app.trajectory = null;
  app.heatmapGrid = null;
  app.result = null;
  clearPosterior();
  app.playing = false;
  app.time = 0;
  showResultSummary(null);
  highlightObservations(null);
  updatePlayback();
}

export function showTrajectory(trajectory) {
  app.trajectory = trajectory;
  if (app.path) app.path.removeFromParent();
  const source = app.model.source;
  const track = trajectory.objects[source] || Object.values(trajectory.objects)[0];
  app.path = track ? trajectorySpline(track) : null;
  if (app.path) {
    app.path.visible = $('show-path').checked;
    world.add(app.path);
  }
  gizmo.detach();
  app.selected = null;
  app.time = 0;
  app.playing = true;
  updateSelectionText();
  updatePlayback();
}

export function showHeatmap(grid) {
  if (app.heatmap) app.heatmap.removeFromParent();
  app.heatmapGrid = grid;
  const area = app.model.startArea;
  const source = app.model.source;
  const surfaces = [...app.nodes].filter(([id, node]) => id !== source && node.visual)
    .map(([, node]) => node.visual);
  const topZ = area ? Math.max(area.min[2], area.max[2]) : 1;
  app.heatmap = heatmapDecal(grid, world, surfaces, topZ);
  app.heatmap.visible = $('show-heatmap').checked;
}

// The sampler's two independent runs disagree (result.json's posterior.agreement): the posterior is
// rugged and its samples, intervals and heatmap are not to be trusted.
export function warnIfRunsDisagree(agreement) {
  if (!agreement || agreement.runs_agree) return;
  notify(`posterior: the sampler's independent runs disagree (R-hat up to ${agreement.max_rhat.toFixed(2)} > `
    + `${agreement.limit}); do not trust these samples`, 'warning');
}

// The result's summary in the panel: how far the answer ends from where the source was seen (the
// END, against the last observation), each observation of a tracked source, when it came to rest,
// the warnings (results.js summarizeResult).
export function showResultSummary(result) {
  const list = $('result-summary');
  list.innerHTML = '';
  const lines = result ? summarizeResult(result) : [];
  for (const line of lines) {
    const li = document.createElement('li');
    li.className = line.kind;
    li.textContent = line.text;
    list.appendChild(li);
  }
  if (!lines.length) {
    const li = document.createElement('li');
    li.className = 'muted';
    li.textContent = 'no result yet';
    list.appendChild(li);
  }
}

// The posterior's samples of a done job (solve with samples, heatmap), when it drew any: returns
// them ([{weight, position}]), or null.
export async function showSamples(jobId) {
  const response = await serverFetch(`jobs/${jobId}/posterior.csv`);
  if (!response.ok) return null; // a job that drew no samples has no posterior.csv
  let samples;
  try {
    samples = parsePosterior(await response.text());
    if (app.samples) app.samples.removeFromParent();
    app.samples = sampleCloud(samples);
    app.samples.visible = $('show-samples').checked;
    world.add(app.samples);
  } catch (err) {
    notify(`posterior samples: ${err.message}`, 'error');
    return null;
  }
  const paths = await serverFetch(`jobs/${jobId}/posterior_paths.csv`);
  if (!paths.ok) return samples;
  try {
    if (app.samplePaths) app.samplePaths.removeFromParent();
    app.samplePaths = samplePaths(parsePosteriorPaths(await paths.text()));
    app.samplePaths.visible = $('show-samples').checked;
    world.add(app.samplePaths);
  } catch (err) {
    notify(`posterior paths: ${err.message}`, 'error');
  }
  return samples;
}

// Set-up poses back (the gizmos edit those), playback stopped.
export function showSetup() {
  app.playing = false;
  if (!app.model) return;
  for (const id of app.nodes.keys()) placeFromModel(id);
  poseRobots(0);
  placeObservations();
  highlightObservations(null);
  updatePlayback();
}

export function applyTime(t) {
  app.time = t;
  for (const [id, track] of Object.entries(app.trajectory.objects)) {
    const node = app.nodes.get(id);
    if (node && node.group.parent === world) applyPose(track, t, node.group); // not while held in VR
  }
  poseRobots(t);
  highlightObservations(t);
}

export function updatePlayback() {
  const duration = app.trajectory?.duration || 0;
  $('play').textContent = app.playing ? 'Pause' : 'Play';
  $('scrub').value = duration ? Math.round((1000 * app.time) / duration) : 0;
  $('time').textContent = `${app.time.toFixed(2)} / ${duration.toFixed(2)} s`;
}

export function play() {
  if (!app.trajectory) return;
  gizmo.detach();
  app.selected = null;
  if (app.time >= app.trajectory.duration) app.time = 0;
  app.playing = true;
  updatePlayback();
}

export function pause() {
  app.playing = false;
  updatePlayback();
}

export function seek(t) {
  if (!app.trajectory) return;
  gizmo.detach();
  app.playing = false;
  applyTime(Math.min(app.trajectory.duration, Math.max(0, t)));
  updatePlayback();
}

$('play').onclick = () => (app.playing ? pause() : play());
$('scrub').oninput = () => seek(((app.trajectory?.duration || 0) * Number($('scrub').value)) / 1000);
$('setup-view').onclick = () => showSetup();
$('show-heatmap').onchange = () => { if (app.heatmap) app.heatmap.visible = $('show-heatmap').checked; };
$('show-samples').onchange = () => {
  for (const shown of [app.samples, app.samplePaths, world.getObjectByName('live-samples')]) {
    if (shown) shown.visible = $('show-samples').checked;
  }
};
$('show-path').onchange = () => { if (app.path) app.path.visible = $('show-path').checked; };
$('show-spheres').onchange = () => {
  const on = $('show-spheres').checked;
  for (const node of app.nodes.values()) {
    if (node.packing) {
      node.packing.visible = on;
      node.visual.visible = !on;
    }
  }
};
