// PLY point clouds (points.ply of a reconstruction) for the 3D view. Pure: no DOM, no three.js.

const HEADER_SEARCH_BYTES = 65536;
const DEFAULT_GREY = 200; // colour of points in a file without red/green/blue
// Size in bytes and DataView reader of each PLY scalar type.
const TYPES = {
  char: [1, "getInt8"], int8: [1, "getInt8"], uchar: [1, "getUint8"], uint8: [1, "getUint8"],
  short: [2, "getInt16"], int16: [2, "getInt16"], ushort: [2, "getUint16"], uint16: [2, "getUint16"],
  int: [4, "getInt32"], int32: [4, "getInt32"], uint: [4, "getUint32"], uint32: [4, "getUint32"],
  float: [4, "getFloat32"], float32: [4, "getFloat32"], double: [8, "getFloat64"], float64: [8, "getFloat64"],
};

// Vertices of an ASCII or binary little-endian PLY file (an ArrayBuffer or a typed array of its bytes):
// {positions: Float32Array (x y z per vertex), colors: Uint8Array (r g b), count}. The vertex element comes
// first; a file that declares more vertices than it holds, or a type PLY does not have, is refused.
export function parsePly(buffer) {
  const bytes = ArrayBuffer.isView(buffer) ? new Uint8Array(buffer.buffer, buffer.byteOffset, buffer.byteLength)
    : new Uint8Array(buffer);
  const marker = new TextEncoder().encode("end_header");
  let end = -1;
  for (let i = 0; i + marker.length <= Math.min(bytes.length, HEADER_SEARCH_BYTES) && end < 0; i++) {
    if (marker.every((b, k) => bytes[i + k] === b)) end = i;
  }
  if (end < 0) throw new Error("points.ply: no end_header");
  const header = new TextDecoder().decode(bytes.subarray(0, end)).split(/\r?\n/);
  const bodyStart = bytes.indexOf(10, end) + 1;
  let format = null, count = 0, inVertex = false;
  const props = [];
  for (const line of header) {
    const words = line.trim().split(/\s+/);
    if (words[0] === "format") format = words[1];
    else if (words[0] === "element") {
      inVertex = words[1] === "vertex";
      if (inVertex) count = Number(words[2]);
      if (inVertex && !(Number.isInteger(count) && count >= 0)) throw new Error(`points.ply: bad vertex count ${words[2]}`);
    } else if (words[0] === "property" && inVertex) {
      if (!TYPES[words[1]]) throw new Error(`points.ply: property ${words[2]} has unknown type ${words[1]}`);
      props.push({ type: words[1], name: words[2] });
    }
  }
  const positions = new Float32Array(3 * count), colors = new Uint8Array(3 * count).fill(DEFAULT_GREY);
  const slot = { x: [positions, 0], y: [positions, 1], z: [positions, 2],
                 red: [colors, 0], green: [colors, 1], blue: [colors, 2] };
  if (format === "ascii") {
    const rows = new TextDecoder().decode(bytes.subarray(bodyStart)).split("\n").filter((row) => row.trim());
    if (rows.length < count) throw new Error(`points.ply: ${count} vertices declared, ${rows.length} rows given`);
    for (let i = 0; i < count; i++) {
      const values = rows[i].trim().split(/\s+/);
      props.forEach((p, k) => { if (slot[p.name]) slot[p.name][0][3 * i + slot[p.name][1]] = +values[k]; });
    }
  } else if (format === "binary_little_endian") {
    const view = new DataView(bytes.buffer, bytes.byteOffset + bodyStart, bytes.byteLength - bodyStart);
    const stride = props.reduce((s, p) => s + TYPES[p.type][0], 0);
    if (count * stride > view.byteLength) {
      throw new Error(`points.ply: ${count} vertices declared, the body holds ${Math.floor(view.byteLength / (stride || 1))}`);
    }
    for (let i = 0; i < count; i++) {
      let offset = i * stride;
      for (const p of props) {
        const [size, reader] = TYPES[p.type];
        if (slot[p.name]) slot[p.name][0][3 * i + slot[p.name][1]] = view[reader](offset, true);
        offset += size;
      }
    }
  } else {
    throw new Error(`points.ply: unsupported format ${format}`);
  }
  return { positions, colors, count };
}
