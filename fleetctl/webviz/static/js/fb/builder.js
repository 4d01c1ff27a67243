// Generic FlatBuffers builder driven by the same layouts as reader.js.
//
// It writes front to back: a table's vtable, then the table, then the objects its offset
// fields point to, so every uoffset points forward (FlatBuffers requires unsigned offsets,
// not a particular order). Scalars are aligned to their size, the table start to 8 bytes.
// Used for the few commands the page sends (goals, initial poses, subscriptions).

import { SCALARS, LayoutError } from "./layout.js";

class Sink {
  constructor(capacity = 256) {
    this.bytes = new Uint8Array(capacity);
    this.view = new DataView(this.bytes.buffer);
    this.pos = 0;
  }

  reserve(n) {
    if (this.pos + n <= this.bytes.length) return;
    let cap = this.bytes.length * 2;
    while (cap < this.pos + n) cap *= 2;
    const next = new Uint8Array(cap);
    next.set(this.bytes);
    this.bytes = next;
    this.view = new DataView(next.buffer);
  }

  /** Pad with zeros until (pos + extra) is a multiple of n. */
  align(n, extra = 0) {
    const pad = (n - ((this.pos + extra) % n)) % n;
    this.reserve(pad);
    this.pos += pad;
  }

  alloc(n) {
    this.reserve(n);
    const at = this.pos;
    this.pos += n;
    return at;
  }

  put(at, kind, value) {
    const v = this.view;
    switch (kind) {
      case "bool": v.setUint8(at, value ? 1 : 0); break;
      case "int8": v.setInt8(at, value); break;
      case "uint8": v.setUint8(at, value); break;
      case "int16": v.setInt16(at, value, true); break;
      case "uint16": v.setUint16(at, value, true); break;
      case "int32": v.setInt32(at, value, true); break;
      case "uint32": v.setUint32(at, value, true); break;
      case "int64": v.setBigInt64(at, BigInt.asIntN(64, toBig(value)), true); break;
      case "uint64": v.setBigUint64(at, BigInt.asUintN(64, toBig(value)), true); break;
      case "float32": v.setFloat32(at, value, true); break;
      case "float64": v.setFloat64(at, value, true); break;
      default: throw new LayoutError(`unknown scalar kind ${kind}`);
    }
  }

  patchOffset(at, target) {
    this.view.setUint32(at, target - at, true);
  }

  finish() {
    return this.bytes.slice(0, this.pos);
  }
}

function toBig(value) {
  return typeof value === "bigint" ? value : BigInt(Math.trunc(Number(value ?? 0)));
}

const utf8 = new TextEncoder();

export class Builder {
  /** @param {import("./layout.js").Layouts} layouts */
  constructor(layouts) {
    this.layouts = layouts;
  }

  /**
   * Encode a message (a plain object; missing fields are left absent = default).
   * @param {string} typeName ROS 2 type of the root table
   * @param {object} msg including `__metadata: {type, topic, no_drop, publish_time_ns, seq}`
   * @returns {Uint8Array} one frame
   */
  encode(typeName, msg) {
    const sink = new Sink();
    const rootAt = sink.alloc(4);
    sink.patchOffset(rootAt, this.table(sink, this.layouts.rootTable(typeName), msg));
    return sink.finish();
  }

  inlineSize(f) {
    if (f.kind === "scalar") return { size: SCALARS[f.scalar].size, align: SCALARS[f.scalar].size };
    if (f.kind === "struct") {
      const s = this.layouts.struct(f.struct);
      return { size: s.size, align: s.align };
    }
    return { size: 4, align: 4 };
  }

  table(sink, layout, value) {
    const present = layout.fields.filter((f) => value?.[f.name] !== undefined && value[f.name] !== null);
    const maxSlot = present.reduce((m, f) => Math.max(m, f.slot), -1);
    sink.align(2);
    const vtable = sink.alloc(4 + 2 * (maxSlot + 1));
    sink.bytes.fill(0, vtable, vtable + 4 + 2 * (maxSlot + 1));
    sink.put(vtable, "uint16", 4 + 2 * (maxSlot + 1));
    sink.align(8);
    const start = sink.alloc(4);
    sink.put(start, "int32", start - vtable);
    // Largest alignment first keeps padding inside the table small.
    const placed = present
      .map((f) => ({ f, ...this.inlineSize(f) }))
      .sort((a, b) => b.align - a.align);
    const offsets = [];
    for (const p of placed) {
      sink.align(p.align);
      const at = sink.alloc(p.size);
      sink.put(vtable + 4 + 2 * p.f.slot, "uint16", at - start);
      offsets.push({ ...p, at });
    }
    sink.put(vtable + 2, "uint16", sink.pos - start);
    for (const { f, at } of offsets) this.fill(sink, f, at, value[f.name], layout.name);
    return start;
  }

  fill(sink, f, at, v, where) {
    switch (f.kind) {
      case "scalar": sink.put(at, f.scalar, v); break;
      case "struct": this.struct(sink, this.layouts.struct(f.struct), at, v); break;
      case "string": sink.patchOffset(at, this.string(sink, String(v))); break;
      case "table": sink.patchOffset(at, this.table(sink, this.layouts.table(f.table), v)); break;
      case "vector": sink.patchOffset(at, this.vector(sink, f.element, v, where)); break;
      default: throw new LayoutError(`${where}.${f.name}: unknown field kind ${f.kind}`);
    }
  }

  struct(sink, layout, at, v) {
    for (const f of layout.fields) {
      if (f.kind === "struct") this.struct(sink, this.layouts.struct(f.struct), at + f.offset, v?.[f.name]);
      else sink.put(at + f.offset, f.scalar, v?.[f.name] ?? SCALARS[f.scalar].zero);
    }
  }

  string(sink, s) {
    const data = utf8.encode(s);
    sink.align(4);
    const at = sink.alloc(4 + data.length + 1);
    sink.put(at, "uint32", data.length);
    sink.bytes.set(data, at + 4);
    sink.bytes[at + 4 + data.length] = 0;
    return at;
  }

  vector(sink, el, items, where) {
    const n = items.length;
    if (el.kind === "scalar" || el.kind === "struct") {
      const { size, align } = this.inlineSize(el);
      sink.align(Math.max(4, align), 4);
      const at = sink.alloc(4 + n * size);
      sink.put(at, "uint32", n);
      for (let i = 0; i < n; i++) this.fill(sink, el, at + 4 + i * size, items[i], where);
      return at;
    }
    sink.align(4);
    const at = sink.alloc(4 + 4 * n);
    sink.put(at, "uint32", n);
    for (let i = 0; i < n; i++) this.fill(sink, el, at + 4 + 4 * i, items[i], where);
    return at;
  }
}
