// Layout descriptions of FlatBuffer tables, as served by `fleetctl webviz` at
// /types/<pkg>/msg/<Name>.json (produced by fleetctl.webviz.layouts from the same type
// registry as the Python codec).
//
// One document per root type:
//   {"type": "sensor_msgs/msg/LaserScan",
//    "tables":  {NAME: {"fields": [{"name", "slot", "kind", ...}]}},
//    "structs": {NAME: {"size", "align", "fields": [{"name", "offset", "kind", ...}]}}}
// Field kinds: {"kind":"scalar","scalar":"float32"}, {"kind":"string"},
// {"kind":"table","table":NAME}, {"kind":"struct","struct":NAME},
// {"kind":"vector","element":{<a field kind without name/slot>}}.

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

/** A merged set of table and struct layouts. */
export class Layouts {
  constructor() {
    this.tables = new Map();
    this.structs = new Map();
    this.roots = new Set();
  }

  /** Merge one served document. */
  add(doc) {
    if (!doc || typeof doc !== "object" || !doc.tables) throw new LayoutError("layout document has no tables");
    for (const [name, t] of Object.entries(doc.tables)) this.tables.set(name, { name, ...t });
    for (const [name, s] of Object.entries(doc.structs ?? {})) this.structs.set(name, { name, ...s });
    this.roots.add(normalizeType(doc.type));
    return this;
  }

  has(typeName) {
    return this.roots.has(normalizeType(typeName));
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
      const resp = await this.fetchFn(`${this.baseUrl}${name}.json`);
      if (!resp.ok) throw new LayoutError(`layout of ${name}: HTTP ${resp.status} ${await resp.text()}`);
      this.layouts.add(await resp.json());
      return this.layouts;
    } catch (err) {
      const e = err instanceof LayoutError ? err : new LayoutError(`layout of ${name}: ${err}`);
      this.failed.set(name, e);
      throw e;
    } finally {
      this.pending.delete(name);
    }
  }
}
