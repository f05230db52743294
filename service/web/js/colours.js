// Colours of registered cameras by registration order. Pure: linear RGB triples in [0, 1].

// HSL -> RGB as three.js's Color.setHSL computes it (h wraps, s and l clamp).
export function hslToRgb(h, s, l) {
  h = ((h % 1) + 1) % 1;
  s = Math.min(1, Math.max(0, s));
  l = Math.min(1, Math.max(0, l));
  if (s === 0) return [l, l, l];
  const p = l <= 0.5 ? l * (1 + s) : l + s - l * s, q = 2 * l - p;
  const channel = (t) => {
    t = ((t % 1) + 1) % 1;
    if (t < 1 / 6) return q + (p - q) * 6 * t;
    if (t < 1 / 2) return p;
    if (t < 2 / 3) return q + (p - q) * 6 * (2 / 3 - t);
    return q;
  };
  return [channel(h + 1 / 3), channel(h), channel(h - 1 / 3)];
}

const LAST_HUE = 0.66; // blue

// Colour of the i-th registered camera of n: red (first) through yellow and green to blue (last).
export const orderColour = (i, n) => hslToRgb((LAST_HUE * i) / Math.max(n - 1, 1), 0.85, 0.55);
