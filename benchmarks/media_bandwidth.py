"""What operators look at, against the Robot Web Tools paper: camera, TF, clouds, maps.

Usage::

    .venv/bin/python benchmarks/media_bandwidth.py [--json] [--camera-seconds S]
        [--tf-seconds S] [--cloud-frames N]

Runs the four media benchmarks in one process, one after the other, and prints one table:
each row a stream as RWT measured it (section IV: Fig. 3, Tables I-III) and as fleetctl
sends it, with RWT's figure, ours and ours / RWT. The measurements are those of

- ``benchmarks/media/camera.py`` ``measure_camera``: a 640 x 480 30 Hz camera as raw
  Image, JPEG quality 90 and fleetctl video (RWT Table I: 12,052 / 1,317 / VP8 342 KB/s);
- ``benchmarks/media/tf.py`` ``measure_tf``: a 52-frame robot's /tf raw and through the
  client's republisher (RWT Fig. 3: 208.5 -> 96.0 KB/s);
- ``benchmarks/media/cloud.py`` ``measure_cloud``: a 640 x 480 RGB-D cloud in full and as
  the viewer encoding at 1 cm (RWT Table II: 5,591.6 -> 568.4 KB/s);
- ``benchmarks/media/map.py`` ``measure_map``: a 2,725 KB-class occupancy grid plain and
  compressed (RWT Table III: 2,725 -> 39 KB).

A benchmark that is missing or fails prints "not measured: <reason>" in its rows; nothing
is filled in for it. Each module's docstring says what its input is. KB = 1000 bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # `media` beside this file

Row = tuple[str, str, float, Any, str]  # name, unit, RWT's figure, ours (or a reason), note


def run(module: str, function: str, **kwargs: Any) -> dict[str, Any] | str:
    """``media.<module>.<function>(**kwargs)``'s result, or why there is none."""
    try:
        measure: Callable[..., dict[str, Any]] = getattr(
            importlib.import_module(f"media.{module}"), function)
    except ModuleNotFoundError as exc:
        if exc.name == f"media.{module}":
            return f"benchmarks/media/{module}.py is not there (yet)"
        return f"benchmarks/media/{module}.py cannot be imported: {exc}"
    except (ImportError, AttributeError) as exc:
        return f"benchmarks/media/{module}.py has no {function}: {exc}"
    try:
        return measure(**kwargs)
    except Exception as exc:  # one failing benchmark must not hide the others
        traceback.print_exc(file=sys.stderr)
        return f"{function} failed: {type(exc).__name__}: {exc}"


def _get(result: dict[str, Any], *keys: str) -> Any:
    """The first of *keys* in *result* (benchmarks name their figures a little differently)."""
    for key in keys:
        node: Any = result
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                break
            node = node[part]
        else:
            return node
    raise KeyError(f"none of {', '.join(keys)} in the result (keys: {', '.join(result)})")


def camera_rows(r: dict[str, Any] | str) -> list[Row]:
    names = [("camera raw Image", 12052.0), ("camera JPEG-90 (RWT: MJPEG)", 1317.0),
             ("camera video (RWT: VP8)", 342.0)]
    if isinstance(r, str):
        return [(n, "KB/s", rwt, r, "") for n, rwt in names]
    rows: list[Row] = []
    for (name, rwt), kind in zip(names, ("raw", "jpeg", "video"), strict=True):
        ours: float | str
        try:
            ours = float(_get(r, f"{kind}_kBps", f"{kind}.kBps", f"{kind}_KBps"))
            note = _camera_note(r, kind)
        except KeyError as exc:
            ours, note = f"not in camera result: {exc}", ""
        rows.append((name, "KB/s", rwt, ours, note))
    return rows


def _camera_note(r: dict[str, Any], kind: str) -> str:
    if kind == "raw":
        return ""
    parts = []
    if kind == "video":
        with contextlib.suppress(KeyError, TypeError, ValueError):
            parts.append(f"{r.get('codec', '?')}, {float(r['ratio_jpeg_video']):.2f}x smaller "
                         f"than JPEG-90 (RWT VP8 3.85x)")
    for label, keys in (("SSIM", (f"{kind}_ssim", f"{kind}.ssim")),
                        ("PSNR", (f"{kind}_psnr_db", f"{kind}_psnr", f"{kind}.psnr_db")),
                        ("enc ms", (f"{kind}_encode_ms", f"{kind}.encode_ms")),
                        ("p50 ms", (f"{kind}_latency_p50_ms", f"{kind}.latency_p50_ms"))):
        with contextlib.suppress(KeyError, TypeError, ValueError):  # not every figure
            parts.append(f"{label} {float(_get(r, *keys)):.3g}")
    return ", ".join(parts)


def tf_rows(r: dict[str, Any] | str) -> list[Row]:
    names = [("TF raw /tf (52 frames)", 208.5), ("TF republished", 96.0)]
    if isinstance(r, str):
        return [(n, "KB/s", rwt, r, "") for n, rwt in names]
    note = (f"{r['ratio']:.1f}x (RWT 2.2x); max error {r['max_error_m'] * 1000:.1f} mm, "
            f"{r['max_error_rad']:.4f} rad")
    return [(names[0][0], "KB/s", 208.5, r["raw_kBps"], ""),
            (names[1][0], "KB/s", 96.0, r["republished_kBps"], note)]


def cloud_rows(r: dict[str, Any] | str) -> list[Row]:
    names = [("cloud full 640x480 (plain)", 5591.6), ("cloud viewer 1 cm (deflate)", 568.4)]
    if isinstance(r, str):
        return [(n, "KB/s", rwt, r, "") for n, rwt in names]
    full_note = (f"at {r['rate_hz']:.2f} Hz (RWT's input rate); deflated "
                 f"{r['full_deflate_kBps']:,.0f}")
    note = (f"{r['ratio_plain']:.1f}x (RWT 9.8x), {r['ratio']:.1f}x vs deflated full; "
            f"{r['kept_points']:,.0f} of {r['valid_points']:,.0f} points, max error "
            f"{r['max_error_m'] * 1000:.1f} mm, {r['encode_ms']:.0f} ms/cloud")
    return [(names[0][0], "KB/s", 5591.6, r["full_kBps"], full_note),
            (names[1][0], "KB/s", 568.4, r["viewer_deflate_kBps"], note)]


def map_rows(r: dict[str, Any] | str) -> list[Row]:
    names = [("map 1650x1650 (frame)", 2725.0), ("map latched (deflate-9, page decodes)", 39.0),
             ("map deflate-1 (a streamed grid)", 39.0), ("map zstd-1", 39.0),
             ("map 732x413 latched (RWT's size)", 39.0)]
    if isinstance(r, str):
        return [(n, "KB", rwt, r, "") for n, rwt in names]
    big, small = r["large"], r["rwt_size"]
    return [
        (names[0][0], "KB", 2725.0, big["frame_bytes"] / 1000, "RWT: 732x413 as JSON"),
        (names[1][0], "KB", 39.0, big["latched_deflate_bytes"] / 1000,
         f"{big['latched_deflate_ms']:.0f} ms once per map"),
        (names[2][0], "KB", 39.0, big["deflate_bytes"] / 1000, f"{big['deflate_ms']:.1f} ms"),
        (names[3][0], "KB", 39.0, big["zstd_bytes"] / 1000,
         f"{big['zstd_ms']:.1f} ms; level 9 {big['zstd9_payload_bytes'] / 1000:.1f}"),
        (names[4][0], "KB", 39.0, small["latched_deflate_bytes"] / 1000,
         f"frame {small['frame_bytes'] / 1000:.1f}"),
    ]


def render(rows: list[Row]) -> str:
    """One table: stream, unit, RWT, ours, ours / RWT, notes."""
    out = [f"{'stream':34}{'unit':>5}{'RWT':>10}{'fleetctl':>10}{'ours/RWT':>10}  notes"]
    for name, unit, rwt, ours, note in rows:
        if isinstance(ours, str):
            out.append(f"{name:34}{unit:>5}{rwt:10,.1f}  not measured: {ours}")
            continue
        out.append(f"{name:34}{unit:>5}{rwt:10,.1f}{ours:10,.1f}{ours / rwt:10.3f}  {note}")
    return "\n".join(out)


def main() -> None:
    """Measure all four and print the table (or JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", action="store_true", help="print all results as JSON")
    parser.add_argument("--camera-seconds", type=float, default=None,
                        help="camera sequence length (default: camera.py's)")
    parser.add_argument("--tf-seconds", type=float, default=60.0, help="simulated TF seconds")
    parser.add_argument("--cloud-frames", type=int, default=5, help="clouds to average over")
    args = parser.parse_args()
    camera_kw = {} if args.camera_seconds is None else {"seconds": args.camera_seconds}
    results: dict[str, dict[str, Any] | str] = {
        "camera": run("camera", "measure_camera", **camera_kw),
        "tf": run("tf", "measure_tf", duration_s=args.tf_seconds),
        "cloud": run("cloud", "measure_cloud", frames=args.cloud_frames),
        "map": run("map", "measure_map"),
    }
    rows = (camera_rows(results["camera"]) + tf_rows(results["tf"])
            + cloud_rows(results["cloud"]) + map_rows(results["map"]))
    if args.json:
        print(json.dumps({"results": results, "rows": [
            {"stream": n, "unit": u, "rwt": rwt, "fleetctl": o if not isinstance(o, str) else None,
             "not_measured": o if isinstance(o, str) else None, "note": note}
            for n, u, rwt, o, note in rows]}, indent=2, default=str))
    else:
        print(render(rows))


if __name__ == "__main__":
    main()
