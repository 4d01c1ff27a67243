"""Soak of the web page left open for hours (a control-room wall monitor).

Usage::

    .venv/bin/python benchmarks/page_soak.py [--minutes 10] [--warmup-cycles 2]
        [--sample-s 10] [--json out.json]

Operators leave the fleet page open for days: does it keep its memory and its speed? Real
parts only: ``fleetctl demo`` (relay, two rclpy sim robots with their clients, the webviz)
on free ports, and the page in the Debian Chromium (Playwright, as
tests/webviz/test_browser.py), signed in as the demo's operator.

The page goes round a cycle of what an operator does (:data:`CYCLE`): robot1's page with
every panel, panels hidden and shown again, the fleet overview, robot2's page, Pause and
Resume, the tab hidden for 20 s and shown again. Headless Chromium does not hide a tab (a
background tab, a minimized window and CDP ``Page.setWebLifecycleState`` "frozen" all left
the page drawing 60 animation frames a second, ``visibilityState`` "visible"), so an init
script does what a hidden tab means to the page: ``requestAnimationFrame`` callbacks are
held until it is shown, and ``document.visibilityState`` says "hidden"; messages keep
coming as they would. The relay is not restarted: ``fleetctl demo`` ends when one of its
children exits.

Every ``--sample-s`` a sample through CDP: the JS heap after a forced
GC (``HeapProfiler.collectGarbage``, ``Runtime.getHeapUsage``), ``Performance.getMetrics``
(DOM nodes, event listeners, documents, layouts and main-thread task time), the renderer and
GPU processes' RSS, each three.js renderer's ``info.memory`` and program count (scene and
cloud), WebGL contexts alive after the GC, WebCodecs decoders not closed and decoded
frames not closed (an init script counts them), robot1's pose latency from the page's own
link-health table, the share of time in long tasks (PerformanceObserver ``longtask``), and
the size of every Map, Set and array reachable from ``window.fleetviz`` (four levels down).

The page differs between its overview and a robot page, so growth is judged on one sample
per cycle taken in the same state (robot1's page, every panel shown, after its dwell), the
warm-up cycles left out. The last half of those samples is cut in two, and a quantity
grows when the floor (minimum) of the second part is above the floor of the first by more
than its tolerance (absolute and relative, :data:`TOLERANCES`) and its least-squares slope
over the last half is positive. A leak raises the floor; a passing spike does not. Speed
(pose latency, long-task and busy shares) is compared by medians, the pose latency over
every sample that has one. Exit
status 1 when something grows, 0 when everything is flat, 2 when the run was too short
to judge (fewer than three cycles after the warm-up; a cycle is about 110 s). At the end, the
renderer's and GPU process's RSS before and after a critical memory-pressure signal (CDP
``Memory.simulatePressureNotification``): what Chromium keeps for reuse and gives back
then is not held by the page.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # tests.webviz.demoproc starts and stops fleetctl demo

from tests.webviz.demoproc import descendants_of, running_demo  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
VIEWPORT: Any = {"width": 1400, "height": 1100}  # Playwright's ViewportSize
BASE_DOMAIN_ID = 86  # robot1 86, robot2 87: away from the tests' ranges and demo's default
UI_TIMEOUT_MS = 30_000
MB = 1024 * 1024

# Counters the page cannot give itself, installed before its scripts: WebGL contexts (weakly
# held, so a context whose canvas was collected is not counted), WebCodecs decoders and the
# frames they output against the frames closed, and long tasks.
PROBE_JS = """
(() => {
  const probe = { contexts: [], decoders: [], seen: new WeakSet(), framesOut: 0,
                  framesClosed: 0, longtaskMs: 0, longtasks: 0 };
  window.__soak = probe;
  const getContext = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, ...rest) {
    const ctx = getContext.call(this, kind, ...rest);
    if (ctx && /webgl/.test(kind) && !probe.seen.has(ctx)) {
      probe.seen.add(ctx);
      probe.contexts.push(new WeakRef(ctx));
    }
    return ctx;
  };
  // WebGL buffers the page holds: created, less those deleted and those whose wrapper the
  // garbage collector took (which is when Chromium frees a buffer nobody deleted).
  probe.glBuffers = 0;
  probe.glBufferBytes = 0;
  probe.glCollected = 0;
  const records = new WeakMap();
  const drop = (rec) => {
    if (!rec.live) return;
    rec.live = false;
    probe.glBuffers--;
    probe.glBufferBytes -= rec.bytes;
  };
  const collected = new FinalizationRegistry((rec) => {
    if (rec.live) probe.glCollected++;
    drop(rec);
  });
  for (const Ctx of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
    if (!Ctx) continue;
    const { createBuffer, deleteBuffer, bufferData } = Ctx.prototype;
    Ctx.prototype.createBuffer = function () {
      const b = createBuffer.call(this);
      if (b) {
        const rec = { bytes: 0, live: true };
        records.set(b, rec);
        collected.register(b, rec);
        probe.glBuffers++;
      }
      return b;
    };
    Ctx.prototype.deleteBuffer = function (b) {
      const rec = b && records.get(b);
      if (rec) drop(rec);
      return deleteBuffer.call(this, b);
    };
    Ctx.prototype.bufferData = function (target, src, ...rest) {
      const binding = target === this.ELEMENT_ARRAY_BUFFER
        ? this.ELEMENT_ARRAY_BUFFER_BINDING : this.ARRAY_BUFFER_BINDING;
      const rec = records.get(this.getParameter(binding));
      if (rec && rec.live) {
        const bytes = typeof src === "number" ? src : (src ? src.byteLength : 0);
        probe.glBufferBytes += bytes - rec.bytes;
        rec.bytes = bytes;
      }
      return bufferData.call(this, target, src, ...rest);
    };
  }
  if (window.VideoDecoder) {
    const Real = window.VideoDecoder;
    window.VideoDecoder = class extends Real {
      constructor(init) {
        super({ ...init, output: (frame) => { probe.framesOut++; return init.output(frame); } });
        probe.decoders.push(new WeakRef(this));
      }
    };
    const close = VideoFrame.prototype.close;
    VideoFrame.prototype.close = function () { probe.framesClosed++; return close.call(this); };
  }
  // A hidden tab, as far as the page can tell: no animation frames (held and run when
  // shown, as Chromium does) and visibilityState "hidden". Headless Chromium never hides a
  // tab itself (a background tab, a minimized window and Page.setWebLifecycleState
  // "frozen" all left it drawing 60 frames a second, visibilityState "visible").
  const raf = window.requestAnimationFrame.bind(window);
  let held = [];
  window.requestAnimationFrame = (cb) => {
    if (!probe.hidden) return raf(cb);
    held.push(cb);
    return 0;
  };
  const visibility = Object.getOwnPropertyDescriptor(Document.prototype, "visibilityState");
  Object.defineProperty(Document.prototype, "visibilityState", {
    configurable: true, get() { return probe.hidden ? "hidden" : visibility.get.call(this); } });
  Object.defineProperty(Document.prototype, "hidden", {
    configurable: true, get() { return !!probe.hidden; } });
  probe.setHidden = (on) => {
    probe.hidden = on;
    document.dispatchEvent(new Event("visibilitychange"));
    if (!on) { const cbs = held; held = []; for (const cb of cbs) raf(cb); }
  };
  try {
    new PerformanceObserver((list) => {
      for (const e of list.getEntries()) { probe.longtaskMs += e.duration; probe.longtasks++; }
    }).observe({ type: "longtask", buffered: true });
  } catch (err) { probe.longtaskError = String(err); }
})();
"""

# One sample of what the page holds (run right after a forced GC).
SAMPLE_JS = """
() => {
  const p = window.__soak, app = window.fleetviz;
  p.contexts = p.contexts.filter((r) => r.deref());
  p.decoders = p.decoders.filter((r) => r.deref());
  const three = (r) => r ? { geometries: r.info.memory.geometries,
    textures: r.info.memory.textures, programs: (r.info.programs || []).length } : null;
  const sizes = {};
  const seen = new WeakSet();
  const skip = new Set(["THREE", "els", "canvas", "renderer"]);
  let paths = 0;
  const walk = (obj, path, depth) => {
    if (!obj || typeof obj !== "object" || depth > 4 || paths > 600) return;
    if (obj instanceof Node || obj instanceof ArrayBuffer || ArrayBuffer.isView(obj)) return;
    if (seen.has(obj)) return;
    seen.add(obj);
    if (obj instanceof Map || obj instanceof Set || Array.isArray(obj)) {
      paths++;
      sizes[path] = (sizes[path] || 0) + (Array.isArray(obj) ? obj.length : obj.size);
      // A collection's members under one path, summed: keys differ between robots.
      let n = 0;
      for (const v of obj.values()) { if (n++ > 50) break; walk(v, path + "[*]", depth + 1); }
      return;
    }
    for (const k of Object.keys(obj)) {
      if (!skip.has(k)) walk(obj[k], path ? path + "." + k : k, depth + 1);
    }
  };
  walk(app, "", 0);
  const robot = app && app.robot;
  let poseLatencyMs = null;
  if (robot && !app.paused) {
    for (const tr of document.querySelectorAll("#health tbody tr")) {
      if (tr.cells[0].textContent === "/" + robot + "/pose") {
        const v = Number(tr.cells[2].textContent);
        poseLatencyMs = Number.isFinite(v) ? v : null;
      }
    }
  }
  return {
    nowMs: performance.now(),
    robot, paused: !!(app && app.paused),
    webglContexts: p.contexts.filter((r) => !r.deref().isContextLost()).length,
    decoders: p.decoders.filter((r) => r.deref().state !== "closed").length,
    framesOpen: p.framesOut - p.framesClosed,
    longtaskMs: p.longtaskMs,
    scene: three(app && app.views && app.views.scene.renderer),
    cloud: three(app && app.views && app.views.cloud.renderer),
    poseLatencyMs,
    collections: sizes,
  };
}
"""


@dataclass(frozen=True)
class Tolerance:
    """How much a quantity may rise over the last half of the run and still be flat.

    Attributes:
        absolute: in the quantity's own unit.
        relative: share of the quantity's value at the start of the last half.
    """

    absolute: float
    relative: float = 0.0

    def allows(self, start: float, rise: float) -> bool:
        return rise <= max(self.absolute, self.relative * abs(start))


TOLERANCES: dict[str, Tolerance] = {
    "heap_mb": Tolerance(1.0, 0.05),
    "buffers_mb": Tolerance(5.0, 0.10),
    "embedder_mb": Tolerance(2.0, 0.10),
    "renderer_rss_mb": Tolerance(20.0, 0.10),
    "gpu_rss_mb": Tolerance(20.0, 0.10),
    "nodes": Tolerance(100, 0.05),
    "listeners": Tolerance(20, 0.05),
    "documents": Tolerance(1),
    "webgl_contexts": Tolerance(0.5),
    "gl_buffers": Tolerance(20, 0.10),
    "gl_buffer_mb": Tolerance(10, 0.10),
    "decoders": Tolerance(0.5),
    "frames_open": Tolerance(3),
    "scene_geometries": Tolerance(5, 0.10),
    "scene_textures": Tolerance(2),
    "scene_programs": Tolerance(2),
    "cloud_geometries": Tolerance(2),
    "cloud_textures": Tolerance(2),
    "cloud_programs": Tolerance(2),
    # Speed: a loaded shared machine makes these noisy; "grows" here means doubling.
    "pose_latency_ms": Tolerance(200, 1.0),
    "longtask_share": Tolerance(0.10),
    "busy_share": Tolerance(0.15),
}
COLLECTION_TOLERANCE = Tolerance(20, 0.20)
SPEED = {"pose_latency_ms", "longtask_share", "busy_share"}  # judged by medians, not floors


@dataclass
class Sample:
    """One sample: the cycle and step it was taken in, and its values by quantity."""

    t_s: float
    cycle: int
    step: str
    values: dict[str, float]
    collections: dict[str, float] = field(default_factory=dict)
    checkpoint: bool = False


class Probe:
    """Reads one page through its CDP session and the processes of its browser."""

    def __init__(self, page: Any, cdp: Any) -> None:
        self.page = page
        self.cdp = cdp
        self.last: dict[str, float] = {}  # cumulative counters at the last sample

    async def sample(self) -> tuple[dict[str, float], dict[str, float]]:
        # What the page holds as it runs, before the forced GC: a WebGL buffer nobody
        # deleted is freed only when the collector takes its wrapper.
        before = await self.page.evaluate(
            "({n: __soak.glBuffers, mb: __soak.glBufferBytes / 1048576, gc: __soak.glCollected})")
        rss = chromium_rss_mb()
        await self.cdp.send("HeapProfiler.collectGarbage")
        heap = await self.cdp.send("Runtime.getHeapUsage")
        metrics = {m["name"]: m["value"] for m in
                   (await self.cdp.send("Performance.getMetrics"))["metrics"]}
        page = await self.page.evaluate(SAMPLE_JS)
        values = {
            "heap_mb": heap["usedSize"] / MB,
            # ArrayBuffers' memory (decoded messages, clouds) is outside the V8 heap.
            "buffers_mb": heap.get("backingStorageSize", math.nan) / MB,
            "embedder_mb": heap.get("embedderHeapUsedSize", math.nan) / MB,
            "nodes": metrics["Nodes"],
            "listeners": metrics["JSEventListeners"],
            "documents": metrics["Documents"],
            "webgl_contexts": page["webglContexts"],
            "decoders": page["decoders"],
            "frames_open": page["framesOpen"],
            "gl_buffers": before["n"],
            "gl_buffer_mb": before["mb"],
            "gl_collected": before["gc"],
            **rss,
        }
        for name in ("scene", "cloud"):
            for key, value in (page[name] or {}).items():
                values[f"{name}_{key}"] = value
        if page["poseLatencyMs"] is not None:
            values["pose_latency_ms"] = page["poseLatencyMs"]
        values.update(self._shares(page, metrics))
        return values, page["collections"]

    def _shares(self, page: dict[str, Any], metrics: dict[str, float]) -> dict[str, float]:
        """Long-task and main-thread busy shares since the last sample, layouts per second."""
        now = {"wall_ms": page["nowMs"], "longtask_ms": page["longtaskMs"],
               "task_ms": metrics["TaskDuration"] * 1000, "layouts": metrics["LayoutCount"]}
        last, self.last = self.last, now
        if not last or now["wall_ms"] <= last["wall_ms"]:
            return {}
        wall = now["wall_ms"] - last["wall_ms"]
        return {
            "longtask_share": (now["longtask_ms"] - last["longtask_ms"]) / wall,
            "busy_share": (now["task_ms"] - last["task_ms"]) / wall,
            "layouts_per_s": (now["layouts"] - last["layouts"]) * 1000 / wall,
        }


def chromium_rss_mb() -> dict[str, float]:
    """RSS (MiB) of this script's Chromium renderer and GPU processes (from /proc)."""
    out = {"renderer_rss_mb": 0.0, "gpu_rss_mb": 0.0}
    for pid, _ in descendants_of(os.getpid()):
        try:
            # Chromium's children rewrite their argv into one string: search it whole.
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
            status = Path(f"/proc/{pid}/status").read_text()
        except OSError:
            continue
        if b"chrom" not in cmdline.split(b" ")[0]:
            continue
        kind = ("renderer_rss_mb" if b"--type=renderer" in cmdline
                else "gpu_rss_mb" if b"--type=gpu-process" in cmdline else None)
        rss = [line for line in status.splitlines() if line.startswith("VmRSS:")]
        if kind and rss:
            out[kind] += int(rss[0].split()[1]) / 1024
    return out


# --- what an operator does ------------------------------------------------------------

Step = Callable[[Any, Any], Awaitable[None]]


async def open_robot(page: Any, robot: str) -> None:
    await page.evaluate(f"location.hash = '#/robot/{robot}'")
    await page.wait_for_function(
        f"fleetviz.robot === '{robot}' && !document.querySelector('#robot').hidden",
        timeout=UI_TIMEOUT_MS)


async def step_robot1(page: Any, _cdp: Any) -> None:
    await open_robot(page, "robot1")


async def step_panels(page: Any, _cdp: Any) -> None:
    for panel in ("scene", "video", "cloud", "gps", "map"):
        await page.uncheck(f"#show-{panel}")
    for panel in ("scene", "video", "cloud", "gps", "map"):
        await page.check(f"#show-{panel}")


async def step_overview(page: Any, _cdp: Any) -> None:
    await page.evaluate("location.hash = '#/'")
    await page.wait_for_function("!document.querySelector('#overview').hidden",
                                 timeout=UI_TIMEOUT_MS)


async def step_robot2(page: Any, _cdp: Any) -> None:
    await open_robot(page, "robot2")


async def step_pause(page: Any, _cdp: Any) -> None:
    await page.click("#pause")
    await page.wait_for_function("fleetviz.paused", timeout=UI_TIMEOUT_MS)


async def step_resume(page: Any, _cdp: Any) -> None:
    await page.click("#pause")
    await page.wait_for_function("!fleetviz.paused", timeout=UI_TIMEOUT_MS)


async def step_hide(page: Any, _cdp: Any) -> None:
    await page.evaluate("__soak.setHidden(true)")


async def step_show(page: Any, _cdp: Any) -> None:
    await page.evaluate("__soak.setHidden(false)")


@dataclass(frozen=True)
class CycleStep:
    """One operator action, then *dwell_s* seconds in the state it leaves."""

    name: str
    action: Step
    dwell_s: float


CYCLE: tuple[CycleStep, ...] = (
    CycleStep("robot1", step_robot1, 20),
    CycleStep("panels", step_panels, 10),
    CycleStep("overview", step_overview, 10),
    CycleStep("robot2", step_robot2, 15),
    CycleStep("pause", step_pause, 10),
    CycleStep("resume", step_resume, 5),
    CycleStep("hidden", step_hide, 20),
    CycleStep("shown", step_show, 5),
)
CHECKPOINT = "robot1"  # the step whose last sample goes into the verdict
MIN_CYCLES = 3  # checkpoint samples after the warm-up needed for a verdict


# --- the run --------------------------------------------------------------------------


async def run(args: argparse.Namespace) -> list[Sample]:
    from playwright.async_api import async_playwright

    deadline = time.monotonic() + args.minutes * 60
    samples: list[Sample] = []
    duration_s = args.minutes * 60 + 300  # the demo stops itself if this script dies
    with tempfile.TemporaryDirectory(prefix="page_soak-") as tmp:
        async with running_demo(Path(tmp) / "demo", args.base_domain_id,
                                extra_args=("--duration", str(duration_s))) as demo, \
                async_playwright() as pw:
            browser = await pw.chromium.launch(executable_path=args.chromium,
                                               args=["--no-sandbox"])
            try:
                page = await browser.new_page(viewport=VIEWPORT)
                await page.add_init_script(PROBE_JS)
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                await sign_in(page, demo.webviz_url, demo.operator_token)
                cdp = await page.context.new_cdp_session(page)
                await cdp.send("Performance.enable")
                probe = Probe(page, cdp)
                start = time.monotonic()
                cycle = 0
                stop = stop_on_signals()
                while time.monotonic() < deadline and not stop.is_set():
                    for step in CYCLE:
                        if stop.is_set():
                            break
                        await step.action(page, cdp)
                        await dwell(step, probe, samples, cycle, start, args.sample_s, stop)
                    print_sample_line(samples, cycle)
                    cycle += 1
                await report_pressure(probe, cdp)
                if errors:
                    print(f"page errors ({len(errors)}): {errors[:5]}", file=sys.stderr)
            finally:
                await browser.close()
    return samples


async def report_pressure(probe: Probe, cdp: Any) -> None:
    """Renderer and GPU RSS before and after a critical memory-pressure signal: what
    Chromium keeps for reuse (and gives back under pressure) is not the page's."""
    before = chromium_rss_mb()
    await cdp.send("Memory.simulatePressureNotification", {"level": "critical"})
    await probe.page.evaluate("new Promise((r) => setTimeout(r, 2000))")  # its purge runs
    after = chromium_rss_mb()
    print(f"at the end: renderer RSS {before['renderer_rss_mb']:.0f} MB, GPU process "
          f"{before['gpu_rss_mb']:.0f} MB; after a critical memory-pressure signal "
          f"{after['renderer_rss_mb']:.0f} and {after['gpu_rss_mb']:.0f} MB")


async def sign_in(page: Any, url: str, token: str) -> None:
    await page.goto(url)
    await page.fill("#token", token)
    await page.click("#signin-button")
    await page.wait_for_function("document.querySelector('#conn-state').textContent === 'open'",
                                 timeout=UI_TIMEOUT_MS)


def stop_on_signals() -> asyncio.Event:
    """An event set by Ctrl-C or SIGTERM: the soak ends its cycle early and still reports
    and stops the demo (a cancelled Playwright call once kept it running for the whole
    run, ignoring SIGINT)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    return stop


async def dwell(step: CycleStep, probe: Probe, samples: list[Sample], cycle: int,
                start: float, sample_s: float, stop: asyncio.Event) -> None:
    """Stay *step.dwell_s* in the step's state, sampling every *sample_s* (last at the end),
    until *stop* is set."""
    end = time.monotonic() + step.dwell_s
    while (left := end - time.monotonic()) > 0:
        # The soak's pace, not a synchronization: a sample every sample_s, or stop.
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), min(sample_s, left))
        if stop.is_set():
            return
        values, collections = await probe.sample()
        samples.append(Sample(time.monotonic() - start, cycle, step.name, values, collections))
    if step.name == CHECKPOINT and samples and samples[-1].step == CHECKPOINT:
        samples[-1].checkpoint = True


# --- the report -----------------------------------------------------------------------

COLUMNS = ("heap_mb", "buffers_mb", "renderer_rss_mb", "gpu_rss_mb", "nodes", "listeners",
           "webgl_contexts", "gl_buffers", "gl_buffer_mb", "gl_collected", "decoders",
           "frames_open", "scene_geometries", "scene_textures", "scene_programs",
           "cloud_geometries", "pose_latency_ms", "longtask_share", "busy_share")
SHORT = {"heap_mb": "heapMB", "buffers_mb": "bufMB", "renderer_rss_mb": "rendMB",
         "gpu_rss_mb": "gpuMB", "nodes": "nodes", "listeners": "lstn", "webgl_contexts": "gl",
         "gl_buffers": "glBuf", "gl_buffer_mb": "glBufMB", "gl_collected": "glGCd",
         "decoders": "dec",
         "frames_open": "vfr", "scene_geometries": "sGeo", "scene_textures": "sTex",
         "scene_programs": "sPrg", "cloud_geometries": "cGeo", "pose_latency_ms": "poseMs",
         "longtask_share": "long", "busy_share": "busy"}


def fmt(value: float | None) -> str:
    if value is None or math.isnan(value):
        return "-"
    if abs(value) < 1 and value != 0:
        return f"{value:.2f}"
    return f"{value:.1f}" if abs(value) < 100 else f"{value:.0f}"


def print_sample_line(samples: list[Sample], cycle: int) -> None:
    if cycle == 0:
        print(f"{'t_s':>6} {'cyc':>3} {'step':<8} " + " ".join(f"{SHORT[c]:>7}" for c in COLUMNS))
    for s in samples:
        if s.cycle == cycle:
            mark = "*" if s.checkpoint else " "
            print(f"{s.t_s:6.0f} {s.cycle:3d} {s.step:<8}{mark}"
                  + " ".join(f"{fmt(s.values.get(c)):>7}" for c in COLUMNS), flush=True)


@dataclass(frozen=True)
class Verdict:
    """One quantity over the checkpoint samples after the warm-up."""

    name: str
    first: float  # median of the first three samples of the last half
    last: float  # median of the last three
    slope_per_h: float  # least-squares slope over the last half, per hour
    grows: bool


def verdict(name: str, points: list[tuple[float, float]], tolerance: Tolerance,
            statistic: Callable[[list[float]], float] = min) -> Verdict | None:
    """Flat or growing over the last half of *points* ((t_s, value), in time order).

    The last half is cut in two and *statistic* of each part compared: by default the
    floor (min), which a leak raises and a passing spike does not (DOM nodes read 658 or
    810 depending on whether a table was just rebuilt; a 30-minute run's medians of three
    called that growth); speed quantities pass ``statistics.median``.
    """
    if len(points) < MIN_CYCLES:
        return None
    half = points[-max(MIN_CYCLES, (len(points) + 1) // 2):]
    cut = len(half) // 2
    first = statistic([v for _, v in half[:cut]])
    last = statistic([v for _, v in half[cut:]])
    slope = least_squares_slope(half) * 3600
    grows = slope > 0 and not tolerance.allows(first, last - first)
    return Verdict(name, first, last, slope, grows)


def least_squares_slope(points: list[tuple[float, float]]) -> float:
    n = len(points)
    mt = sum(t for t, _ in points) / n
    mv = sum(v for _, v in points) / n
    den = sum((t - mt) ** 2 for t, _ in points)
    return 0.0 if den == 0 else sum((t - mt) * (v - mv) for t, v in points) / den


def verdicts(samples: list[Sample], warmup_cycles: int) -> list[Verdict]:
    marks = [s for s in samples if s.checkpoint and s.cycle >= warmup_cycles]
    out: list[Verdict] = []
    for name, tolerance in TOLERANCES.items():
        speed = name in SPEED
        # The pose's latency is noisy sample to sample (18-867 ms at one step of one run):
        # every sample that has it, from a robot page, rather than one per cycle.
        source = ([s for s in samples if s.cycle >= warmup_cycles] if name == "pose_latency_ms"
                  else marks)
        points = [(s.t_s, s.values[name]) for s in source if name in s.values]
        judged = verdict(name, points, tolerance, statistics.median if speed else min)
        if judged is not None:
            out.append(judged)
    paths = sorted({p for s in marks for p in s.collections})
    for path in paths:
        points = [(s.t_s, s.collections.get(path, 0.0)) for s in marks]
        if (v := verdict(f"fleetviz.{path}", points, COLLECTION_TOLERANCE)) is not None:
            out.append(v)
    return out


def print_verdicts(results: list[Verdict], shown_collections: int = 15) -> None:
    print(f"\n{'quantity':<44} {'first':>9} {'last':>9} {'slope/h':>9}  verdict")
    collections = [v for v in results if v.name.startswith("fleetviz.")]
    biggest = sorted(collections, key=lambda v: -v.last)[:shown_collections]
    for v in results:
        if v.name.startswith("fleetviz.") and not v.grows and v not in biggest:
            continue
        print(f"{v.name:<44} {fmt(v.first):>9} {fmt(v.last):>9} {fmt(v.slope_per_h):>9}  "
              f"{'GROWS' if v.grows else 'flat'}")
    print(f"({len(collections)} collections under window.fleetviz checked; the largest "
          f"{len(biggest)} and every growing one shown)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the soak")
    parser.add_argument("--warmup-cycles", type=int, default=2,
                        help="cycles left out of the verdict (caches filling, JIT)")
    parser.add_argument("--sample-s", type=float, default=10.0, help="seconds between samples")
    parser.add_argument("--base-domain-id", type=int, default=BASE_DOMAIN_ID)
    parser.add_argument("--chromium", default=CHROMIUM)
    parser.add_argument("--json", type=Path, help="write every sample and verdict here")
    parser.add_argument("--judge", type=Path, metavar="JSON",
                        help="judge the samples of an earlier run's --json instead of running")
    args = parser.parse_args()
    if args.judge:
        samples = [Sample(**s) for s in json.loads(args.judge.read_text())["samples"]]
    else:
        samples = asyncio.run(run(args))
    results = verdicts(samples, args.warmup_cycles)
    print_verdicts(results)
    if args.json:
        args.json.write_text(json.dumps({
            "samples": [s.__dict__ for s in samples],
            "verdicts": [v.__dict__ for v in results],
        }, indent=1))
    cycles = len({s.cycle for s in samples if s.checkpoint and s.cycle >= args.warmup_cycles})
    if cycles < MIN_CYCLES:
        print(f"too short to judge: {cycles} cycles after the warm-up ({MIN_CYCLES} needed)")
        return 2
    growing = [v.name for v in results if v.grows]
    print("verdict: " + (f"grows: {', '.join(growing)}" if growing else "flat"))
    return 1 if growing else 0


if __name__ == "__main__":
    sys.exit(main())
