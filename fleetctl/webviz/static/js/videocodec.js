// What the page must know about one foxglove_msgs/msg/CompressedVideo message before it
// hands it to WebCodecs: is it a keyframe, and which codec string configures a decoder.
//
// Pure (no DOM): tests run it under node. Bitstream forms are Foxglove's: H.264/H.265 in
// Annex B with the parameter sets in each keyframe, VP8/VP9 frames, AV1 as OBUs in the
// low-overhead bitstream format. Only the first bytes of each unit are read.

/** Video formats the page knows, and the codec string used when the bitstream does not say. */
export const DEFAULT_CODECS = {
  h264: "avc1.42E01E", // Constrained Baseline, level 3.0: replaced by the keyframe's SPS
  h265: "hev1.1.6.L93.B0", // Main, level 3.1
  vp8: "vp8",
  vp9: "vp09.00.10.08", // profile 0, level 1.0, 8 bit: replaced by the frame's profile
  av1: "av01.0.04M.08", // Main, level 3.0, 8 bit: replaced by the sequence header's profile
};

const hex2 = (n) => n.toString(16).toUpperCase().padStart(2, "0");

/** Normalized format name: "H264", "avc" -> "h264"; null when unknown. */
export function normalizeFormat(format) {
  const f = String(format ?? "").trim().toLowerCase().replace(/[^a-z0-9]/g, "");
  const alias = { h264: "h264", avc: "h264", avc1: "h264", h265: "h265", hevc: "h265", vp8: "vp8", vp9: "vp9", av1: "av1", av01: "av1" };
  return alias[f] ?? null;
}

/** Annex B NAL units: [{start, end}] of each payload (after its start code). */
export function annexBUnits(data) {
  const starts = [];
  for (let i = 0; i + 2 < data.length; i++) {
    if (data[i] === 0 && data[i + 1] === 0 && data[i + 2] === 1) {
      starts.push(i + 3);
      i += 2;
    }
  }
  return starts.map((s, k) => {
    let end = k + 1 < starts.length ? starts[k + 1] - 3 : data.length;
    while (end > s && data[end - 1] === 0) end--; // the zero of a 4-byte start code
    return { start: s, end };
  });
}

function inspectH264(data) {
  let key = false;
  let codec = null;
  for (const { start, end } of annexBUnits(data)) {
    if (end <= start) continue;
    const type = data[start] & 0x1f;
    if (type === 5) key = true; // IDR slice
    if (type === 7 && end - start >= 4) codec = `avc1.${hex2(data[start + 1])}${hex2(data[start + 2])}${hex2(data[start + 3])}`;
  }
  return { key, codec };
}

function inspectH265(data) {
  let key = false;
  for (const { start, end } of annexBUnits(data)) {
    if (end <= start) continue;
    const type = (data[start] >> 1) & 0x3f;
    if (type >= 16 && type <= 23) key = true; // IRAP: BLA, IDR, CRA
  }
  return { key, codec: null };
}

function inspectVp8(data) {
  // RFC 6386 section 9.1: frame tag bit 0 is 0 for a key frame, which then carries the
  // start code 9d 01 2a.
  const key = data.length >= 6 && (data[0] & 1) === 0 && data[3] === 0x9d && data[4] === 0x01 && data[5] === 0x2a;
  return { key, codec: null };
}

class Bits {
  constructor(bytes, pos = 0, end = bytes.length) {
    this.bytes = bytes;
    this.bit = pos * 8;
    this.end = end * 8;
  }

  read(n) {
    let v = 0;
    for (let i = 0; i < n; i++) {
      if (this.bit >= this.end) throw new RangeError("truncated");
      v = (v << 1) | ((this.bytes[this.bit >> 3] >> (7 - (this.bit & 7))) & 1);
      this.bit++;
    }
    return v;
  }
}

function inspectVp9(data) {
  // VP9 spec section 6.2 uncompressed_header(): frame_marker (2), profile (2 bits, low
  // first), reserved bit in profile 3, show_existing_frame, frame_type (0 = KEY_FRAME).
  try {
    const b = new Bits(data);
    if (b.read(2) !== 2) return { key: false, codec: null };
    const low = b.read(1);
    const profile = (b.read(1) << 1) | low;
    if (profile === 3) b.read(1);
    if (b.read(1) === 1) return { key: false, codec: null }; // show_existing_frame
    const key = b.read(1) === 0;
    const depth = profile >= 2 ? "10" : "08";
    return { key, codec: key ? `vp09.${hex2(profile)}.10.${depth}` : null };
  } catch {
    return { key: false, codec: null };
  }
}

function leb128(data, pos) {
  let value = 0;
  for (let i = 0; i < 8; i++) {
    if (pos + i >= data.length) return null;
    const b = data[pos + i];
    value += (b & 0x7f) * 2 ** (7 * i);
    if (!(b & 0x80)) return { value, next: pos + i + 1 };
  }
  return null;
}

/** AV1 OBUs of a temporal unit: [{type, start, end}] of each payload. */
export function av1Obus(data) {
  const out = [];
  for (let pos = 0; pos < data.length;) {
    const h = data[pos];
    const type = (h >> 3) & 0x0f;
    const hasSize = (h >> 1) & 1;
    let at = pos + 1 + ((h >> 2) & 1); // extension header byte
    let end = data.length;
    if (hasSize) {
      const size = leb128(data, at);
      if (!size) break;
      at = size.next;
      end = at + size.value;
    }
    if (end > data.length || at > end) break;
    out.push({ type, start: at, end });
    pos = end;
  }
  return out;
}

const OBU_SEQUENCE_HEADER = 1;
const OBU_FRAME_HEADER = 3;
const OBU_FRAME = 6;

function inspectAv1(data) {
  let reduced = false;
  let codec = null;
  let key = false;
  for (const obu of av1Obus(data)) {
    try {
      const b = new Bits(data, obu.start, obu.end);
      if (obu.type === OBU_SEQUENCE_HEADER) {
        // AV1 spec 5.5.1: seq_profile (3), still_picture (1), reduced_still_picture_header (1).
        const profile = b.read(3);
        b.read(1);
        reduced = b.read(1) === 1;
        codec = `av01.${profile}.04M.08`;
      } else if (obu.type === OBU_FRAME_HEADER || obu.type === OBU_FRAME) {
        // 5.9.2: with a reduced header every frame is a key frame; else show_existing_frame
        // (1), then frame_type (2), KEY_FRAME = 0.
        if (reduced) key = true;
        else if (b.read(1) === 0 && b.read(2) === 0) key = true;
      }
    } catch {
      // A truncated OBU is not a keyframe; the decoder will say what is wrong with it.
    }
  }
  return { key, codec };
}

const INSPECT = { h264: inspectH264, h265: inspectH265, vp8: inspectVp8, vp9: inspectVp9, av1: inspectAv1 };

/**
 * Inspect one encoded video unit.
 * @param {string} format the message's `format` ("h264", "vp8", "vp9", "av1", "h265")
 * @param {Uint8Array} data the message's `data`
 * @returns {{format: string|null, key: boolean, codec: string|null}} `format` null when
 *     unknown; `codec` the WebCodecs codec string (the bitstream's, else the default)
 */
export function inspectVideo(format, data) {
  const f = normalizeFormat(format);
  if (!f) return { format: null, key: false, codec: null };
  const { key, codec } = INSPECT[f](data);
  return { format: f, key, codec: codec ?? DEFAULT_CODECS[f] };
}
