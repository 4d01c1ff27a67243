"""Write an e2e run's results: ``report.json``, ``report.md`` and PNG plots.

A result is a plain JSON-ready dict per scenario with ``name``, ``status`` (``pass``,
``fail`` or ``not_run``), ``criteria`` (list of ``{name, value, bound, ok}``), ``notes`` and
``series`` (plot data, written to the JSON too so plots can be redrawn).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def overall_ok(results: Sequence[dict[str, Any]]) -> bool:
    """True when every scenario passed (a scenario that did not run is a failure)."""
    return bool(results) and all(r["status"] == "pass" for r in results)


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:.3g}"
    return str(value)


def table(results: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of every criterion (also what the terminal shows)."""
    lines = ["| scenario | status | criterion | value | bound | ok |",
             "|---|---|---|---|---|---|"]
    for r in results:
        crits = r.get("criteria") or [{"name": "-", "value": "-", "bound": "-", "ok": "-"}]
        for c in crits:
            lines.append(f"| {r['name']} | {r['status']} | {c['name']} | {_fmt(c['value'])} | "
                         f"{_fmt(c['bound'])} | {c['ok']} |")
    return "\n".join(lines)


def write(out_dir: Path, environment: dict[str, Any], results: list[dict[str, Any]]) -> Path:
    """Write JSON, Markdown and plots into *out_dir*; returns the Markdown path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = {"environment": environment, "ok": overall_ok(results), "scenarios": results}
    (out_dir / "report.json").write_text(json.dumps(doc, indent=2, default=str))
    md = ["# fleetctl e2e report", ""]
    md += [f"- {k}: {v}" for k, v in environment.items()]
    md += ["", table(results), ""]
    for r in results:
        md.append(f"## {r['name']}: {r['status']}")
        md += [f"- {n}" for n in r.get("notes", [])]
        for plot in _plots(out_dir, r):
            md.append(f"![{r['name']}]({plot.name})")
        md.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(md))
    return path


def legend_once(spans: list[list[Any]]) -> list[tuple[float, float, str | None]]:
    """*spans* ``[x0, x1, label]`` with each label kept on its first span only, so fifteen
    link cuts make one legend entry, not fifteen (matplotlib leaves ``None`` out)."""
    seen: set[str] = set()
    out = []
    for x0, x1, label in spans:
        out.append((x0, x1, None if label in seen else label))
        seen.add(label)
    return out


def _plots(out_dir: Path, result: dict[str, Any]) -> list[Path]:
    # Imported here: matplotlib is a dev/report dependency, and the images (which import
    # every CLI module) do not ship it.
    import matplotlib

    matplotlib.use("Agg")  # no display in containers or CI
    import matplotlib.pyplot as plt

    written = []
    for i, plot in enumerate(result.get("plots", [])):
        fig, ax = plt.subplots(figsize=(8, 4))
        for label, (xs, ys) in plot["lines"].items():
            ax.plot(xs, ys, marker=plot.get("marker", ""), linestyle=plot.get("style", "-"),
                    markersize=3, label=label)
        for x0, x1, label in legend_once(plot.get("spans", [])):
            ax.axvspan(x0, x1, color="red", alpha=0.15, label=label)
        ax.set_xlabel(plot["xlabel"])
        ax.set_ylabel(plot["ylabel"])
        if plot.get("logy"):
            ax.set_yscale("log")
        ax.set_title(plot["title"])
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
        path = out_dir / f"{result['name']}-{i}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written
