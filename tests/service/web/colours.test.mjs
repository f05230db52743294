// Camera colours by registration order (service/web/js/colours.js), checked against three.js's own HSL.
import assert from "node:assert/strict";
import { test } from "node:test";

import { hslToRgb, orderColour } from "../../../service/web/js/colours.js";
import { Color } from "../../../service/web/vendor/three/three.module.min.js";

test("the first registered camera is red, the last blue, the middle one green", () => {
  const [first, middle, last] = [orderColour(0, 5), orderColour(2, 5), orderColour(4, 5)];
  assert.ok(first[0] > 0.9 && first[1] < 0.2 && first[2] < 0.2, `first ${first}`);
  assert.ok(middle[1] > 0.9 && middle[0] < 0.2 && middle[2] < 0.2, `middle ${middle}`);
  assert.ok(last[2] > 0.9 && last[0] < 0.2 && last[1] < 0.2, `last ${last}`);
  assert.deepEqual(orderColour(0, 1), orderColour(0, 5)); // a single camera is "first"
});

test("colours are three.js's Color.setHSL, so the 3D view looks as before", () => {
  for (const [h, s, l] of [[0, 0.85, 0.55], [0.33, 0.85, 0.55], [0.66, 0.85, 0.55], [0.9, 0.5, 0.3],
                           [1.25, 0.2, 0.7], [-0.1, 1.5, 0.5], [0.4, 0, 0.6]]) {
    const three = new Color().setHSL(h, s, l);
    const ours = hslToRgb(h, s, l);
    [three.r, three.g, three.b].forEach((c, k) => assert.ok(Math.abs(c - ours[k]) < 1e-12, `hsl ${h} ${s} ${l}`));
  }
});
