// The user's permissions as the server's welcome frame states them (docs/design.md
// section 2). The server checks every frame anyway; the page uses these only to say
// plainly, before anything is sent, what the user may not do.

/** Compile an RE2 full-match rule as a JS RegExp, or null if JS cannot parse it. */
function fullMatch(re) {
  try {
    return new RegExp(`^(?:${re})$`, "u");
  } catch {
    return null; // conservative: a rule we cannot read grants nothing here
  }
}

export class Rules {
  /** @param {Array<{topic: string, op: string}>} rules */
  constructor(rules = []) {
    this.rules = rules.map((r) => ({ op: r.op, re: fullMatch(r.topic), topic: r.topic }));
  }

  /** Every rule could be read here: what the page infers from them holds (a rule JS
   *  cannot parse grants nothing here, but may grant something on the server). */
  get readable() {
    return this.rules.every((r) => r.re !== null);
  }

  allows(topic, op) {
    return this.rules.some((r) => r.re && (r.op === op || r.op === "both") && r.re.test(topic));
  }

  canSend(topic) {
    return this.allows(topic, "send");
  }

  canReceive(topic) {
    return this.allows(topic, "receive");
  }
}
