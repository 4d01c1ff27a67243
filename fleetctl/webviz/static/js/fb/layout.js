// Layouts of FlatBuffer tables, as served by `fleetctl webviz` at
// /types/<pkg>/msg/<Name>.json: the output of fleetctl.wire.schema.describe(), the same
// MessageLayout objects the Python codec encodes and decodes with:
//   {"root": NAME, "metadata": "fleetctl_msgs/msg/MsgMetadata",
//    "tables":  {NAME: {"first_slot": 0|1, "fields": [{"name", "slot", "kind", "element"?, "type"?}]}},
//    "structs": {NAME: {"size_bytes", "align_bytes", "fields": [{"name", "offset", "element"}]}}}
// with kind one of scalar, string, struct, table, scalar_vector, string_vector,
// struct_vector, table_vector; `element` is the ROS base type, `type` the nested message.
//
// They are converted once into the reader's internal form: field kinds
// {"kind":"scalar","scalar":"float32"}, {"kind":"string"}, {"kind":"table","table":NAME},
// {"kind":"struct","struct":NAME}, {"kind":"vector","element":<kind>}; a root table gets
// field 0 {"name":"__metadata","kind":"table","table":<metadata>} (design.md section 1).

export const SCALARS = {
  bool: { size: 1, zero: false },
  int8: { size: 1, zero: 0 }, uint8: { size: 1, zero: 0 },
  int16: { size: 2, zero: 0 }, uint16: { size: 2, zero: 0 },
  int32: { size: 4, zero: 0 }, uint32: { size: 4, zero: 0 },
  int64: { size: 8, zero: 0n }, uint64: { size: 8, zero: 0n },
  float32: { size: 4, zero: 0 }, float64: { size: 8, zero: 0 },
};

export class LayoutError extends Error {
  constructor(message) {
    super(message);
    this.name = "LayoutError";
  }
}

/** `pkg/Name` and bare control names -> `pkg/msg/Name` (docs/design.md section 1). */
export function normalizeType(name) {
  if (name === "RobofleetSubscription" || name === "RobofleetStatus") return `amrl_msgs/msg/${name}`;
  const parts = name.split("/");
  if (parts.length === 2) return `${parts[0]}/msg/${parts[1]}`;
  return name;
}

// ROS base types -> reader scalar names (byte is int8 and char uint8, as in rosbags).
const ROS_SCALAR = { byte: "int8", char: "uint8" };

function scalarKind(element) {
  const scalar = ROS_SCALAR[element] ?? element;
  if (!SCALARS[scalar]) throw new LayoutError(`unknown scalar type ${element}`);
  return { kind: "scalar", scalar };
}

function elementKind(kind, f) {
  switch (kind) {
    case "scalar": return scalarKind(f.element);
    case "string": return { kind: "string" };
    case "table": return { kind: "table", table: f.type };
    case "struct": return { kind: "struct", struct: f.type };
    default: throw new LayoutError(`${f.name}: unknown field kind ${kind}`);
  }
}

/** One field of a describe() table in the reader's form. */
export function convertField(f) {
  const vector = /^(scalar|string|struct|table)_vector$/.exec(f.kind);
  const kind = vector ? { kind: "vector", element: elementKind(vector[1], f) } : elementKind(f.kind, f);
  return { name: f.name, slot: f.slot, ...kind };
}

function convertStruct(s) {
  return {
    size: s.size_bytes,
    align: s.align_bytes,
    fields: s.fields.map((f) => ({ name: f.name, offset: f.offset, ...scalarKind(f.element) })),
  };
}

/** A merged set of table and struct layouts. */
export class Layouts {
  constructor() {
    this.tables = new Map();
    this.structs = new Map();
    this.roots = new Map(); // root type -> its table with __metadata as field 0
  }

  /** Merge one describe() document. */
  add(doc) {
    if (!doc || typeof doc !== "object" || !doc.tables || !doc.root || !doc.metadata) {
      throw new LayoutError("layout document lacks root, metadata or tables");
    }
    for (const [name, t] of Object.entries(doc.tables)) {
      if (!this.tables.has(name)) this.tables.set(name, { name, fields: t.fields.map(convertField) });
    }
    for (const [name, s] of Object.entries(doc.structs ?? {})) {
      if (!this.structs.has(name)) this.structs.set(name, { name, ...convertStruct(s) });
    }
    const root = this.table(doc.root);
    const meta = { name: "__metadata", slot: 0, kind: "table", table: doc.metadata };
    this.roots.set(doc.root, { name: root.name, fields: [meta, ...root.fields] });
    return this;
  }

  has(typeName) {
    return this.roots.has(normalizeType(typeName));
  }

  /** The table of a root type, field 0 being __metadata. */
  rootTable(typeName) {
    const t = this.roots.get(normalizeType(typeName));
    if (!t) throw new LayoutError(`no layout for root type ${typeName}`);
    return t;
  }

  table(name) {
    const t = this.tables.get(normalizeType(name)) ?? this.tables.get(name);
    if (!t) throw new LayoutError(`no layout for table ${name}`);
    return t;
  }

  struct(name) {
    const s = this.structs.get(normalizeType(name)) ?? this.structs.get(name);
    if (!s) throw new LayoutError(`no layout for struct ${name}`);
    return s;
  }
}

/**
 * Fetches layouts on demand from the webviz server; one request per type, cached,
 * failures remembered so an unknown type is not fetched again on every frame.
 */
export class LayoutLoader {
  /**
   * @param {string|(() => string)} baseUrl where `<type>.json` files are; a function is
   *   asked at every fetch (relay replicas: the replica the page is connected to now).
   */
  constructor(baseUrl = "types/", fetchFn = globalThis.fetch?.bind(globalThis)) {
    this.layouts = new Layouts();
    this.baseUrl = baseUrl;
    this.fetchFn = fetchFn;
    this.pending = new Map();
    this.failed = new Map();
  }

  /** Resolve when the type's layout is loaded; reject with LayoutError otherwise. */
  async ensure(typeName) {
    const name = normalizeType(typeName);
    if (this.layouts.has(name)) return this.layouts;
    if (this.failed.has(name)) throw this.failed.get(name);
    if (!this.pending.has(name)) this.pending.set(name, this.fetchOne(name));
    return this.pending.get(name);
  }

  async fetchOne(name) {
    try {
      const base = typeof this.baseUrl === "function" ? this.baseUrl() : this.baseUrl;
      const resp = await this.fetchFn(`${base}${name}.json`);
      if (!resp.ok) {
        // The server answered: it has no such type. Remembered (no fetch per frame).
        const e = new LayoutError(`layout of ${name}: HTTP ${resp.status} ${await resp.text()}`);
        this.failed.set(name, e);
        throw e;
      }
      this.layouts.add(await resp.json());
      return this.layouts;
    } catch (err) {
      // Not answered (a replica going away): not remembered, the next frame asks again.
      throw err instanceof LayoutError ? err : new LayoutError(`layout of ${name}: ${err}`);
    } finally {
      this.pending.delete(name);
    }
  }
}
