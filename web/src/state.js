// The viewer's state, shared by its modules: the scene model, what is drawn for it, the jobs and
// results; and the notifications list.
export const $ = (id) => document.getElementById(id);

export const app = {
  model: null,
  nodes: new Map(), // id -> {group, visual, packing}
  files: null, // uploaded files by name, or null: meshes come from the server's scene root
  ghost: null, // the target: a translucent copy of the source at the last observed pose
  observations: [], // every <target>: {index, id, group, label, ...} (observations.js)
  observationLine: null, // dashed line through them in time order
  selected: null,
  trajectory: null,
  path: null,
  heatmap: null,
  heatmapGrid: null,
  samples: null, // the posterior samples' start points (THREE.Points)
  samplePaths: null, // a few posterior samples' trajectories (THREE.Group of faint lines)
  time: 0,
  playing: false,
  jobs: new Map(), // job_id -> {kind, state, requestId}
  requests: new Map(), // request_id -> kind
  modeRequests: new Map(), // request_id -> the mode whose past a simulate job plays
  modePlaying: null, // that mode's index in the Result panel's list
  region: null, // the 90 % credible region drawn: {group, from, mass, cells, cellCount, area, level}
  current: null, // the job the chart follows
  result: null,
  notifications: [],
  loading: null,
  startArea: null,
};

export function notify(text, kind = 'info') {
  app.notifications.push({ kind, text, at: Date.now() });
  const li = document.createElement('li');
  li.className = kind;
  li.textContent = text;
  $('notifications').prepend(li);
  while ($('notifications').children.length > 8) $('notifications').lastChild.remove();
  setTimeout(() => li.remove(), kind === 'error' ? 20000 : 8000);
}
