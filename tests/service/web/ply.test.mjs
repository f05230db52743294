// Reading points.ply for the 3D view (service/web/js/ply.js): ASCII and binary, what the reconstruction
// writes (estimation.io.export.write_ply, given by the Python test that runs these), and broken files.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { test } from "node:test";

import { parsePly } from "../../../service/web/js/ply.js";

const encode = (text) => new TextEncoder().encode(text);

function concat(...parts) {
  const out = new Uint8Array(parts.reduce((n, p) => n + p.byteLength, 0));
  let at = 0;
  for (const p of parts) { out.set(new Uint8Array(p.buffer ?? p, p.byteOffset ?? 0, p.byteLength), at); at += p.byteLength; }
  return out;
}

test("an ASCII file gives positions and colours in vertex order", () => {
  const ply = parsePly(encode("ply\r\nformat ascii 1.0\r\nelement vertex 2\r\nproperty float x\r\nproperty float y\r\n"
    + "property float z\r\nproperty uchar red\r\nproperty uchar green\r\nproperty uchar blue\r\nend_header\r\n"
    + "1 2 3 255 0 10\n-0.5 0.25 4e2 1 2 3\n").buffer);
  assert.equal(ply.count, 2);
  assert.deepEqual([...ply.positions], [1, 2, 3, -0.5, 0.25, 400]);
  assert.deepEqual([...ply.colors], [255, 0, 10, 1, 2, 3]);
});

test("a binary file with doubles, extra properties and no colours reads its x y z, points grey", () => {
  const header = encode("ply\nformat binary_little_endian 1.0\ncomment made by hand\nelement vertex 2\n"
    + "property double x\nproperty double y\nproperty double z\nproperty short nx\nproperty float confidence\n"
    + "element face 0\nproperty list uchar int vertex_indices\nend_header\n");
  const body = new DataView(new ArrayBuffer(2 * (3 * 8 + 2 + 4)));
  [[1.5, -2, 3.25, 7, 0.5], [0, 1e3, -1e-3, -1, 1]].forEach((v, i) => {
    const at = i * 30;
    v.slice(0, 3).forEach((c, k) => body.setFloat64(at + 8 * k, c, true));
    body.setInt16(at + 24, v[3], true);
    body.setFloat32(at + 26, v[4], true);
  });
  const ply = parsePly(concat(header, body));
  assert.equal(ply.count, 2);
  assert.deepEqual([...ply.positions], [1.5, -2, 3.25, 0, 1000, Math.fround(-1e-3)]);
  assert.deepEqual([...ply.colors], [200, 200, 200, 200, 200, 200]);
});

test("a file declaring more vertices than it holds, or an unknown type, is refused naming the file", () => {
  const header = (format, count, type = "float") => encode(`ply\nformat ${format} 1.0\nelement vertex ${count}\n`
    + `property ${type} x\nproperty float y\nproperty float z\nend_header\n`);
  assert.throws(() => parsePly(concat(header("binary_little_endian", 3), new Float32Array(6))),
    /points.ply: 3 vertices declared, the body holds 2/);
  assert.throws(() => parsePly(concat(header("ascii", 2), encode("1 2 3\n"))), /points.ply: 2 vertices declared, 1 rows/);
  assert.throws(() => parsePly(header("ascii", 1, "float128")), /points.ply: property x has unknown type float128/);
  assert.throws(() => parsePly(header("ascii", -1)), /points.ply: bad vertex count -1/);
  assert.throws(() => parsePly(header("binary_big_endian", 0)), /unsupported format binary_big_endian/);
  assert.throws(() => parsePly(encode("ply\nformat ascii 1.0\n")), /points.ply: no end_header/);
});

// The reconstruction's own writer, binary and ASCII, against the points it was given (from the Python side).
const fixtures = process.env.SFMNERF_WEB_FIXTURES;
test("what the reconstruction writes reads back as written", { skip: !fixtures && "run by tests/service/test_web_modules.py" }, () => {
  const expected = JSON.parse(readFileSync(join(fixtures, "points.json"), "utf8"));
  for (const name of ["points_binary.ply", "points_ascii.ply"]) {
    const ply = parsePly(readFileSync(join(fixtures, name)));
    assert.equal(ply.count, expected.points.length, name);
    assert.deepEqual([...ply.positions], expected.points.flat().map(Math.fround), name);
    assert.deepEqual([...ply.colors], expected.colors.flat(), name);
  }
});
