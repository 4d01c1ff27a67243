// Generic FlatBuffers reader driven by a JSON layout (see ./layout.js).
//
// The wire format (docs/design.md section 1): one FlatBuffer per frame, root table field 0
// is MsgMetadata, ROS fields follow. Every read is bounds-checked against the buffer and a
// malformed frame throws DecodeError; it never reads outside the frame. Vectors of numbers
// are returned as typed-array *views* on the frame when aligned (zero copy), else copied.

import { SCALARS } from "./layout.js";

export class DecodeError extends Error {
  constructor(message) {
    super(message);
    this.name = "DecodeError";
  }
}

const MAX_DEPTH = 64; // a hostile frame cannot make us recurse without bound

const TYPED = {
  int8: Int8Array, uint8: Uint8Array, int16: Int16Array, uint16: Uint16Array,
  int32: Int32Array, uint32: Uint32Array, int64: BigInt64Array, uint64: BigUint64Array,
  float32: Float32Array, float64: Float64Array,
};

const utf8 = new TextDecoder("utf-8", { fatal: false });

/** A bounds-checked view of one frame. */
export class Frame {
  /** @param {Uint8Array} bytes */
  constructor(bytes) {
    if (!(bytes instanceof Uint8Array)) bytes = new Uint8Array(bytes);
    this.bytes = bytes;
    this.view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    this.length = bytes.byteLength;
  }

  check(pos, size, what) {
    if (!Number.isInteger(pos) || pos < 0 || pos + size > this.length) {
      throw new DecodeError(`${what}: offset ${pos}+${size} outside frame of ${this.length} bytes`);
    }
  }

  scalar(pos, kind, what) {
    const s = SCALARS[kind];
    if (!s) throw new DecodeError(`${what}: unknown scalar kind ${kind}`);
    this.check(pos, s.size, what);
    const v = this.view;
    switch (kind) {
      case "bool": return v.getUint8(pos) !== 0;
      case "int8": return v.getInt8(pos);
      case "uint8": return v.getUint8(pos);
      case "int16": return v.getInt16(pos, true);
      case "uint16": return v.getUint16(pos, true);
      case "int32": return v.getInt32(pos, true);
      case "uint32": return v.getUint32(pos, true);
      case "int64": return v.getBigInt64(pos, true);
      case "uint64": return v.getBigUint64(pos, true);
      case "float32": return v.getFloat32(pos, true);
      case "float64": return v.getFloat64(pos, true);
      default: throw new DecodeError(`${what}: unknown scalar kind ${kind}`);
    }
  }

  u32(pos, what) { return this.scalar(pos, "uint32", what); }

  /** Follow the uoffset stored at pos. */
  deref(pos, what) {
    const target = pos + this.u32(pos, what);
    this.check(target, 4, what);
    return target;
  }

  string(pos, what) {
    const len = this.u32(pos, what);
    this.check(pos + 4, len, what);
    return utf8.decode(this.bytes.subarray(pos + 4, pos + 4 + len));
  }

  /** Position of a table field's data, or 0 when the field is absent. */
  fieldPos(table, slot, what) {
    const vtable = table - this.scalar(table, "int32", what);
    this.check(vtable, 4, `${what} vtable`);
    const vsize = this.scalar(vtable, "uint16", what);
    const tsize = this.scalar(vtable + 2, "uint16", what);
    const entry = 4 + 2 * slot;
    if (entry + 2 > vsize) return 0;
    this.check(vtable, vsize, `${what} vtable`);
    const off = this.scalar(vtable + entry, "uint16", what);
    if (off === 0) return 0;
    if (off >= tsize) throw new DecodeError(`${what}: field offset ${off} past table size ${tsize}`);
    return table + off;
  }

  /** A vector of numbers as a typed array: a view when aligned, a copy otherwise. */
  numbers(pos, kind, what) {
    const n = this.u32(pos, what);
    if (kind === "bool") {
      this.check(pos + 4, n, what);
      return Array.from(this.bytes.subarray(pos + 4, pos + 4 + n), (b) => b !== 0);
    }
    const T = TYPED[kind];
    if (!T) throw new DecodeError(`${what}: no vector of ${kind}`);
    const size = T.BYTES_PER_ELEMENT;
    this.check(pos + 4, n * size, what);
    const start = this.bytes.byteOffset + pos + 4;
    if (start % size === 0) return new T(this.bytes.buffer, start, n);
    return new T(this.bytes.buffer.slice(start, start + n * size));
  }
}

/** Decodes frames of any type whose layout is known. */
export class Reader {
  /** @param {import("./layout.js").Layouts} layouts */
  constructor(layouts) {
    this.layouts = layouts;
  }

  /**
   * Decode a whole frame.
   * @param {Uint8Array|ArrayBuffer} bytes one WebSocket binary frame
   * @param {string} typeName ROS 2 type of the root table
   * @returns {object} the message, with `__metadata` as read from field 0
   */
  decode(bytes, typeName) {
    const frame = bytes instanceof Frame ? bytes : new Frame(bytes);
    const root = frame.deref(0, "root offset");
    return this.table(frame, root, this.layouts.rootTable(typeName), 0);
  }

  table(frame, pos, layout, depth) {
    if (depth > MAX_DEPTH) throw new DecodeError(`${layout.name}: nested too deep`);
    const out = {};
    for (const f of layout.fields) {
      const what = `${layout.name}.${f.name}`;
      const at = frame.fieldPos(pos, f.slot, what);
      out[f.name] = at === 0 ? this.absent(f) : this.value(frame, at, f, what, depth);
    }
    return out;
  }

  absent(f) {
    switch (f.kind) {
      case "scalar": return f.default ?? SCALARS[f.scalar].zero;
      case "string": return "";
      case "vector": return f.element.kind === "scalar" ? new (TYPED[f.element.scalar] ?? Array)(0) : [];
      case "table": return this.emptyTable(this.layouts.table(f.table));
      case "struct": return this.emptyStruct(this.layouts.struct(f.struct));
      default: throw new DecodeError(`${f.name}: unknown field kind ${f.kind}`);
    }
  }

  emptyTable(layout) {
    const out = {};
    for (const f of layout.fields) out[f.name] = this.absent(f);
    return out;
  }

  emptyStruct(layout) {
    const out = {};
    for (const f of layout.fields) {
      out[f.name] = f.kind === "struct" ? this.emptyStruct(this.layouts.struct(f.struct)) : SCALARS[f.scalar].zero;
    }
    return out;
  }

  value(frame, at, f, what, depth) {
    switch (f.kind) {
      case "scalar": return frame.scalar(at, f.scalar, what);
      case "string": return frame.string(frame.deref(at, what), what);
      case "table": return this.table(frame, frame.deref(at, what), this.layouts.table(f.table), depth + 1);
      case "struct": return this.struct(frame, at, this.layouts.struct(f.struct), what);
      case "vector": return this.vector(frame, frame.deref(at, what), f.element, what, depth);
      default: throw new DecodeError(`${what}: unknown field kind ${f.kind}`);
    }
  }

  struct(frame, at, layout, what) {
    frame.check(at, layout.size, what);
    const out = {};
    for (const f of layout.fields) {
      out[f.name] = f.kind === "struct"
        ? this.struct(frame, at + f.offset, this.layouts.struct(f.struct), what)
        : frame.scalar(at + f.offset, f.scalar, `${what}.${f.name}`);
    }
    return out;
  }

  vector(frame, pos, el, what, depth) {
    if (el.kind === "scalar") return frame.numbers(pos, el.scalar, what);
    const n = frame.u32(pos, what);
    const out = [];
    if (el.kind === "struct") {
      const layout = this.layouts.struct(el.struct);
      frame.check(pos + 4, n * layout.size, what);
      for (let i = 0; i < n; i++) out.push(this.struct(frame, pos + 4 + i * layout.size, layout, what));
      return out;
    }
    frame.check(pos + 4, n * 4, what);
    for (let i = 0; i < n; i++) {
      const item = frame.deref(pos + 4 + 4 * i, `${what}[${i}]`);
      if (el.kind === "string") out.push(frame.string(item, what));
      else if (el.kind === "table") out.push(this.table(frame, item, this.layouts.table(el.table), depth + 1));
      else throw new DecodeError(`${what}: no vector of ${el.kind}`);
    }
    return out;
  }
}

/**
 * Read only the metadata (field 0) of a frame, without knowing its type's layout.
 * The metadata layout is fixed by the contract, so this needs no schema.
 * @returns {{type: string, topic: string, no_drop: boolean, publish_time_ns: bigint, seq: bigint,
 *     latched: boolean}} (`latched`: slot 5, absent in older frames = false)
 */
export function readMetadata(bytes) {
  const frame = bytes instanceof Frame ? bytes : new Frame(bytes);
  const root = frame.deref(0, "root offset");
  const at = frame.fieldPos(root, 0, "__metadata");
  if (at === 0) throw new DecodeError("frame has no __metadata (field 0)");
  const m = frame.deref(at, "__metadata");
  const field = (slot, kind, zero) => {
    const p = frame.fieldPos(m, slot, `__metadata.${slot}`);
    if (p === 0) return zero;
    return kind === "string" ? frame.string(frame.deref(p, "__metadata"), "__metadata") : frame.scalar(p, kind, "__metadata");
  };
  return {
    type: field(0, "string", ""),
    topic: field(1, "string", ""),
    no_drop: field(2, "bool", false),
    publish_time_ns: field(3, "uint64", 0n),
    seq: field(4, "uint64", 0n),
    latched: field(5, "bool", false),
  };
}
