// The server calls the page makes: all relative URLs, so the page talks only to the server
// that served it.

import { decodeCells } from './cells.js';

async function json(response) {
  const body = await response.json().catch(() => ({}));
  if (!response.ok) {
    const error = new Error(body.error || `${response.status} ${response.statusText}`);
    error.status = response.status;
    throw error;
  }
  return body;
}

const post = (url, body) =>
  fetch(url, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) }).then(json);

const mapUrl = (map) => `/v1/maps/${encodeURIComponent(map)}`;

const xyz = (v) => v.map((c) => Number(c).toFixed(4)).join(',');

export const listMaps = () => fetch('/v1/maps').then(json).then((b) => b.maps);

export const recentPoses = (map) => fetch(`${mapUrl(map)}/poses`).then(json).then((b) => b.poses);

// Binary cells: `opts` may hold min, max ([x, y, z]), coarsen and since.
export async function fetchCells(map, opts = {}) {
  const q = new URLSearchParams();
  if (opts.min) q.set('min', xyz(opts.min));
  if (opts.max) q.set('max', xyz(opts.max));
  if (opts.coarsen) q.set('coarsen', String(opts.coarsen));
  if (opts.since !== undefined) q.set('since', String(opts.since));
  const response = await fetch(`${mapUrl(map)}/cells?${q}`);
  if (!response.ok) await json(response);
  return decodeCells(await response.arrayBuffer());
}

const thresholdParams = (th) => ({ p_free: th.p_free, p_occ: th.p_occ, var_max: th.var_max });

export function cellAt(map, point, th) {
  const q = new URLSearchParams({ at: point.join(','), ...thresholdParams(th) });
  return fetch(`${mapUrl(map)}/cell?${q}`).then(json);
}

export const boxCounts = (map, min, max, th) =>
  post(`${mapUrl(map)}/query/box`, { min, max, counts_only: true, thresholds: thresholdParams(th) });

export const castRay = (map, origin, direction, maxRange, th) =>
  post(`${mapUrl(map)}/query/rays`, {
    rays: [{ origin, direction, max_range: maxRange }],
    thresholds: thresholdParams(th),
  });

// Server-sent change stream from `since`; `onUpdate` gets each parsed message.
export function watch(map, since, onUpdate, onState) {
  const source = new EventSource(`${mapUrl(map)}/updates?since=${since}`);
  source.onmessage = (e) => onUpdate(JSON.parse(e.data));
  source.onopen = () => onState('live');
  source.onerror = () => onState(source.readyState === EventSource.CLOSED ? 'closed' : 'reconnecting');
  return source;
}
