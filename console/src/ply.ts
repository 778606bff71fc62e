// A binary little-endian PLY vertex reader: x, y, z (any float/int type) and red, green,
// blue (uchar, or float 0..1) into typed arrays, for the snapshot clouds the API serves.
// ASCII and big-endian files are refused with a clear error (the API writes binary LE).

export interface Cloud {
  positions: Float32Array; // x, y, z per point, environment frame, metres
  colors: Uint8Array | null; // r, g, b per point, 0..255
  count: number;
}

const SIZES: Record<string, [number, string]> = {
  char: [1, "Int8"], int8: [1, "Int8"],
  uchar: [1, "Uint8"], uint8: [1, "Uint8"],
  short: [2, "Int16"], int16: [2, "Int16"],
  ushort: [2, "Uint16"], uint16: [2, "Uint16"],
  int: [4, "Int32"], int32: [4, "Int32"],
  uint: [4, "Uint32"], uint32: [4, "Uint32"],
  float: [4, "Float32"], float32: [4, "Float32"],
  double: [8, "Float64"], float64: [8, "Float64"],
};

interface Prop {
  name: string;
  type: string;
  offset: number;
}

export function parsePly(buffer: ArrayBuffer): Cloud {
  const head = new Uint8Array(buffer, 0, Math.min(buffer.byteLength, 64 * 1024));
  const text = new TextDecoder("latin1").decode(head);
  const end = text.indexOf("end_header");
  if (!text.startsWith("ply") || end < 0) throw new Error("not a PLY file (no 'ply' / 'end_header')");
  const nl = text.indexOf("\n", end);
  const bodyStart = nl + 1;
  const lines = text.slice(0, end).split(/\r?\n/);
  let format = "";
  const elements: Array<{ name: string; count: number; props: Prop[]; stride: number; list: boolean }> = [];
  for (const line of lines) {
    const parts = line.trim().split(/\s+/);
    if (parts[0] === "format") format = parts[1];
    else if (parts[0] === "element") elements.push({ name: parts[1], count: Number(parts[2]), props: [], stride: 0, list: false });
    else if (parts[0] === "property") {
      const el = elements[elements.length - 1];
      if (!el) throw new Error("PLY property before any element");
      if (parts[1] === "list") {
        el.list = true;
        continue;
      }
      const size = SIZES[parts[1]];
      if (!size) throw new Error(`PLY property type ${parts[1]} unknown`);
      el.props.push({ name: parts[2], type: parts[1], offset: el.stride });
      el.stride += size[0];
    }
  }
  if (format !== "binary_little_endian") throw new Error(`PLY format ${format} not supported (binary_little_endian only)`);
  const vertex = elements[0];
  if (!vertex || vertex.name !== "vertex") throw new Error("PLY has no leading vertex element");
  if (vertex.list) throw new Error("PLY vertex element with list properties");
  const count = vertex.count;
  if (bodyStart + count * vertex.stride > buffer.byteLength) throw new Error("PLY body is truncated");
  const prop = (n: string) => vertex.props.find((p) => p.name === n);
  const px = prop("x"), py = prop("y"), pz = prop("z");
  if (!px || !py || !pz) throw new Error("PLY vertices lack x, y, z");
  const positions = new Float32Array(count * 3);
  const stride = vertex.stride;
  const fast = px.type === "float" && py.type === "float" && pz.type === "float" && px.offset === 0 && py.offset === 4 && pz.offset === 8;
  const view = new DataView(buffer, bodyStart, count * stride);
  const red = prop("red") ?? prop("r"), green = prop("green") ?? prop("g"), blue = prop("blue") ?? prop("b");
  const colors = red && green && blue ? new Uint8Array(count * 3) : null;
  const bytes = new Uint8Array(buffer, bodyStart, count * stride);
  if (fast && stride % 4 === 0 && bodyStart % 4 === 0) {
    const f = new Float32Array(buffer, bodyStart, (count * stride) / 4);
    const s4 = stride / 4;
    for (let i = 0; i < count; i++) {
      positions[i * 3] = f[i * s4];
      positions[i * 3 + 1] = f[i * s4 + 1];
      positions[i * 3 + 2] = f[i * s4 + 2];
    }
  } else {
    const getter = (p: Prop) => {
      const name = `get${SIZES[p.type][1]}` as "getFloat32";
      return (o: number) => view[name](o, true);
    };
    const gx = getter(px), gy = getter(py), gz = getter(pz);
    for (let i = 0, o = 0; i < count; i++, o += stride) {
      positions[i * 3] = gx(o + px.offset);
      positions[i * 3 + 1] = gy(o + py.offset);
      positions[i * 3 + 2] = gz(o + pz.offset);
    }
  }
  if (colors && red && green && blue) {
    if (red.type === "uchar" || red.type === "uint8") {
      for (let i = 0, o = 0; i < count; i++, o += stride) {
        colors[i * 3] = bytes[o + red.offset];
        colors[i * 3 + 1] = bytes[o + green.offset];
        colors[i * 3 + 2] = bytes[o + blue.offset];
      }
    } else {
      for (let i = 0, o = 0; i < count; i++, o += stride) {
        colors[i * 3] = Math.round(255 * view.getFloat32(o + red.offset, true));
        colors[i * 3 + 1] = Math.round(255 * view.getFloat32(o + green.offset, true));
        colors[i * 3 + 2] = Math.round(255 * view.getFloat32(o + blue.offset, true));
      }
    }
  }
  return { positions, colors, count };
}
