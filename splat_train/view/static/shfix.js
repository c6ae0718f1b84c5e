// Full-precision SH bands for Spark's extended splats. Spark 2.2.0 stores each SH coefficient's
// RGB triple as one word (encodeExtRgb): an exponent floor(log2(max)) and 8-bit mantissas
// clamped at 255, which cuts the triple's largest channel down to the power of two below it
// (up to 2x). This re-encodes the bands from the PLY with one exponent more, which the same
// decoder reads exactly (mantissa in [128, 255]). Layout: 15 words per splat in the textures
// sh1 (bands 1-4), sh2 (5-8), sh3a (9-12), sh3b (13-15).

function plyFloatLayout(bytes) {
  // 3DGS PLY header -> {offset of the data, stride in floats, index of each property}; null if
  // not an all-float binary little-endian vertex list.
  const head = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 65536)));
  const end = head.indexOf("end_header\n");
  if (end < 0 || !head.includes("format binary_little_endian")) return null;
  const props = [];
  for (const line of head.slice(0, end).split("\n")) {
    const t = line.trim().split(/\s+/);
    if (t[0] === "element" && t[1] !== "vertex" && props.length) break;
    if (t[0] === "property") {
      if (t[1] !== "float" && t[1] !== "float32") return null;
      props.push(t[2]);
    }
  }
  const index = Object.fromEntries(props.map((p, i) => [p, i]));
  return { offset: end + "end_header\n".length, stride: props.length, index };
}

function encodeExtRgb(r, g, b) {
  const m = Math.max(Math.abs(r), Math.abs(g), Math.abs(b));
  if (!(m > 0)) return 0;
  const base = Math.min(31, Math.max(0, Math.floor(Math.log2(m)) + 16));
  const div = Math.pow(2, base - 15) / 255;
  const q = (v) => Math.min(255, Math.round(Math.abs(v) / div));
  const signs = (r < 0 ? 1 : 0) | (g < 0 ? 2 : 0) | (b < 0 ? 4 : 0);
  return (q(r) | (q(g) << 8) | (q(b) << 16) | (((base << 3) | signs) << 24)) >>> 0;
}

export function fixShPrecision(splats, bytes) {
  const extra = splats && splats.extra;
  if (!extra || !extra.sh1) return "no SH bands";
  const layout = plyFloatLayout(bytes);
  if (!layout) return "not an all-float 3DGS PLY";
  const nRest = Object.keys(layout.index).filter((k) => k.startsWith("f_rest_")).length;
  const K = nRest / 3;  // bands per channel (3, 8 or 15)
  const n = splats.numSplats;
  const data = new Float32Array(bytes.buffer.slice(bytes.byteOffset + layout.offset,
                                                   bytes.byteOffset + layout.offset + n * layout.stride * 4));
  if (data.length < n * layout.stride) return "PLY shorter than its splat count";
  const rest0 = layout.index["f_rest_0"];
  const targets = [["sh1", "sh1Texture"], ["sh2", "sh2Texture"], ["sh3a", "sh3TextureA"], ["sh3b", "sh3TextureB"]];
  for (let t = 0; t < targets.length; t++) {
    const arr = extra[targets[t][0]];
    if (!arr) continue;
    for (let i = 0; i < n; i++) {
      const row = i * layout.stride + rest0;
      for (let w = 0; w < 4; w++) {
        const j = t * 4 + w;  // band index 0..15
        if (j >= K) break;
        arr[i * 4 + w] = encodeExtRgb(data[row + j], data[row + K + j], data[row + 2 * K + j]);
      }
    }
    const tex = extra[targets[t][1]];
    if (tex && tex.value) tex.value.needsUpdate = true;
  }
  return "applied";
}
