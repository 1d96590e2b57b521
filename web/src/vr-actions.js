// What the VR menu's buttons do (vr-menu.js draws them, vr.js hit-tests them): timed targets added
// in front of the eyes, deleted and shifted in time; objects added there, made the source or fixed,
// removed; a solve. Its top line names the selection (the object or target grabbed last).
import { isObservation, observationId, observationOf } from './selection.js';
import { $, app } from './state.js';

// The selection id of the observation a group draws.
export function observationIdOf(group) {
  const target = app.model.targets[group.userData.observation];
  return target ? observationId(target) : null;
}

// What the VR menu's top line says: the selection (the object or target grabbed last).
export function menuStatus(menu) {
  const id = app.selected;
  let text = 'grab an object or a target to select it';
  if (isObservation(id)) {
    const t = observationOf(id) && app.model.targets[observationOf(id).index];
    text = t ? `${t.last ? 'target' : `target ${t.index + 1}`}: ${t.time == null ? 'at the end' : `${t.time.toFixed(2)} s`}` : text;
  } else if (id && app.model?.object(id)) {
    text = `${id}: ${id === app.model.source ? 'the source' : (app.model.isFixed(id) ? 'fixed' : 'movable')}`;
  }
  menu.setStatus(text);
}

// A VR menu button (vr-menu.js) pressed: at, where an added target or object goes (the scene's
// frame); h: main.js's actions (addTimedTarget, deleteTarget, spawn, setSource, setFixed,
// removeSelected, run, changed, observationsChanged, objectsChanged).
export async function pressMenu(name, at, h) {
  if (!app.model) throw new Error('load a scene first');
  const id = app.selected;
  const obs = observationOf(id);
  const object = !isObservation(id) && id && app.model.object(id) ? id : null;
  const nudge = (dt) => {
    const t = obs && app.model.targets[obs.index];
    if (!t || t.time == null) throw new Error('grab a timed target first');
    app.model.setObservation(t.index, { time: Math.max(0, Number((t.time + dt).toFixed(3))) });
    h.changed();
    h.observationsChanged();
  };
  switch (name) {
    case 'add-target': h.addTimedTarget(null, at); break;
    case 'delete-target': {
      const timed = app.model.targets.filter((t) => t.time != null);
      const index = obs ? obs.index : timed[timed.length - 1]?.index;
      if (index === undefined) throw new Error('no timed target to delete');
      h.deleteTarget(index);
      break;
    }
    case 'time-down': nudge(-0.05); break;
    case 'time-up': nudge(0.05); break;
    case 'box': case 'sphere': case 'cylinder': await h.spawn(name, at); break;
    case 'mesh': {
      const kind = $('spawn-kind').value.startsWith('mesh:') ? $('spawn-kind').value
        : [...$('spawn-kind').options].map((o) => o.value).find((v) => v.startsWith('mesh:'));
      if (!kind) throw new Error('the scene root has no meshes to add');
      await h.spawn(kind, at);
      break;
    }
    case 'source':
      if (!object) throw new Error('grab an object first');
      h.setSource(object);
      break;
    case 'fixed':
      if (!object || object === app.model.source) throw new Error('grab an object (not the source) first');
      h.setFixed(object, !app.model.isFixed(object));
      h.objectsChanged();
      break;
    case 'remove':
      if (!object) throw new Error('grab an object first');
      h.removeSelected(object);
      break;
    case 'solve': h.run('solve'); break;
    default: break;
  }
}
