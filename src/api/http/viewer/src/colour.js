// Colour scales for the cells and the legend that explains them.

// Viridis at 0, ¼, ½, ¾ and 1 (perceptually uniform, readable by colour-blind people).
const STOPS = [
  [0.267, 0.005, 0.329],
  [0.229, 0.322, 0.546],
  [0.128, 0.567, 0.551],
  [0.369, 0.789, 0.383],
  [0.993, 0.906, 0.144],
];

// Writes the colour of t ∈ [0, 1] (clamped) into out[at..at + 3].
export function ramp(t, out, at) {
  const x = Math.min(1, Math.max(0, Number.isFinite(t) ? t : 0)) * (STOPS.length - 1);
  const i = Math.min(STOPS.length - 2, Math.floor(x));
  const f = x - i;
  for (let k = 0; k < 3; k++) out[at + k] = STOPS[i][k] * (1 - f) + STOPS[i + 1][k] * f;
}

export const CSS_GRADIENT = `linear-gradient(to right, ${STOPS.map(
  (c) => `rgb(${c.map((v) => Math.round(v * 255)).join(',')})`,
).join(', ')})`;

// What each colour mode maps to [0, 1], and how the legend labels its ends.
export function scaleFor(mode, extent) {
  switch (mode) {
    case 'probability':
      return { title: 'occupancy probability', lo: 0, hi: 1, value: (f, i) => f.probability[i] };
    case 'variance':
      // The Beta variance never exceeds ¼.
      return { title: 'variance', lo: 0, hi: 0.25, value: (f, i) => f.variance[i] };
    default: {
      const lo = extent ? extent.min[2] : 0;
      const hi = extent ? Math.max(extent.max[2], lo + 0.1) : 3;
      return { title: 'height z (m)', lo, hi, value: (f, i) => f.centres[3 * i + 2] };
    }
  }
}

export function renderLegend(element, scale) {
  const fmt = (v) => (Math.abs(v) >= 10 ? v.toFixed(0) : v.toFixed(2));
  element.innerHTML = '';
  const title = document.createElement('div');
  title.textContent = scale.title;
  const bar = document.createElement('div');
  bar.className = 'legend-bar';
  bar.style.background = CSS_GRADIENT;
  const ends = document.createElement('div');
  ends.className = 'legend-ends';
  ends.innerHTML = `<span>${fmt(scale.lo)}</span><span>${fmt(scale.hi)}</span>`;
  element.append(title, bar, ends);
}
