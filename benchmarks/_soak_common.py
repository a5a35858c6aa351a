"""Shared by the soak benchmarks (``soak.py``, ``soak_memory.py``): the Victoria Park log
replayed as revisits, the resident set size now, and the ``--set KEY=VALUE`` parser. A helper
module, not a script; each benchmark imports it explicitly (the script's own folder is on
``sys.path`` when it runs, from any working directory)."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["GAP_S", "parse_settings", "revisit_drive", "rss_now_mb"]

GAP_S = 1.0  # standstill between passes


def revisit_drive(vp: Any, passes: int) -> tuple[Any, list[tuple[float, float]]]:
    """``vp`` driven ``passes`` times, forward and backward alternately (see module doc).

    Returns the new :class:`~stemmap.datasets.victoria_park.VictoriaPark` and the time span
    (s) of every pass.
    """
    from stemmap.slam.base import Controls, TreeFrames

    c, fr = vp.controls, vp.frames
    t0 = float(min(c.times[0], fr.times[0], vp.gps_times[0]))
    t1 = float(max(c.times[-1], fr.times[-1], vp.gps_times[-1]))
    span = t1 - t0
    det = [fr.frame(f) for f in range(len(fr))]
    ct, cv, cs, ft, fd, gt, gx, spans = [], [], [], [], [], [], [], []
    for p in range(passes):
        base = t0 + p * (span + GAP_S)
        spans.append((base, base + span))
        if p % 2 == 0:
            ct.append(c.times - t0 + base)
            cv.append(c.speed)
            cs.append(c.steer)
            ft.append(fr.times - t0 + base)
            fd += det
            gt.append(vp.gps_times - t0 + base)
            gx.append(vp.gps_xy)
        else:
            # control i holds on [t_i, t_i+1): backwards it holds from the image of t_i+1
            ct.append(base + (t1 - c.times[1:][::-1]))
            cv.append(-c.speed[:-1][::-1])
            cs.append(c.steer[:-1][::-1])
            ft.append(base + (t1 - fr.times[::-1]))
            fd += det[::-1]
            gt.append(base + (t1 - vp.gps_times[::-1]))
            gx.append(vp.gps_xy[::-1])
    counts = [len(d[0]) for d in fd]
    frames = TreeFrames(
        np.concatenate(ft),
        np.concatenate(([0], np.cumsum(counts))).astype(np.int64),
        *(np.concatenate([d[k] for d in fd]) for k in range(3)),
    )
    controls = Controls(np.concatenate(ct), np.concatenate(cv), np.concatenate(cs), c.kind)
    rep = dataclasses.replace(
        vp,
        controls=controls,
        frames=frames,
        gps_times=np.concatenate(gt),
        gps_xy=np.concatenate(gx),
    )
    return rep, spans


def rss_now_mb() -> float:
    """Resident set size now (``VmRSS``; 0 where /proc is missing)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024.0, 1)
    except OSError:
        pass
    return 0.0


def parse_settings(ap: argparse.ArgumentParser, items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` overrides (values parsed as JSON, else kept as strings)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            ap.error(f"--set expects KEY=VALUE, got {item!r}")
        try:
            out[key.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            out[key.strip()] = raw
    return out
