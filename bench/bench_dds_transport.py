"""Which Fast DDS transport moves 640×480 float frames between node processes best.

Three transports, each a sender and a receiver process of
``endo_bringup.frame_probe`` (run through ``endo_io.process.run_node`` like
every node): a reliable publisher of 640×480 32FC1 frames (1.2 MB) at 30 Hz
and a best-effort subscriber, as correction → SFS:

* ``DEFAULT``: Fast DDS's builtin transports (512 KB shared-memory segments,
  so a frame goes over UDP in fragments), ``FASTDDS_BUILTIN_TRANSPORTS=DEFAULT``;
* ``LARGE_DATA``: ``FASTDDS_BUILTIN_TRANSPORTS=LARGE_DATA`` (Jazzy's builtin
  large-data mode: shared memory and TCP for data, UDP for discovery);
* ``endo3d profile``: no variable set, so the processes get what
  ``endo_io.dds_transport`` gives by default (the 64 MB shared-memory profile).

Each transport runs ``ROUNDS`` times interleaved (so load changes hit all
alike); the table gives frames received of sent, latency median and 95th
percentile, and each figure as a ratio to the endo3d profile of the same run.
Replaces "## DDS transport for large frames" of docs/benchmarks.md, keeping
the previous run's table below the new one. Run by hand, twice:
``.venv/bin/python bench/bench_dds_transport.py``.
"""

from __future__ import annotations

import datetime
import os
import platform
from collections import defaultdict

import numpy as np
from machine import cpu_model
from results import BENCHMARKS, replace_section

from endo_bringup.frame_probe import ProbeError, ProbeResult, run_probe

FRAMES = 150
ROUNDS = 3
SECTION = "## DDS transport for large frames"
TRANSPORTS = {
    "DEFAULT": {"FASTDDS_BUILTIN_TRANSPORTS": "DEFAULT"},
    "LARGE_DATA": {"FASTDDS_BUILTIN_TRANSPORTS": "LARGE_DATA"},
    "endo3d profile": {},
}
REFERENCE = "endo3d profile"
CONCLUSION = (
    "Every endo3d node gives itself the endo3d profile (`endo_io.dds_transport`): in both "
    "runs below it delivered every frame, while Fast DDS's defaults and its `LARGE_DATA` "
    "builtin transports lost about half of them at this load (the machine is shared; the "
    "latencies are dominated by scheduling and differ between runs, the received counts do "
    "not)."
)


def _env(extra: dict[str, str]) -> dict[str, str]:
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
                     "FASTDDS_BUILTIN_TRANSPORTS")
    }  # fmt: skip
    env.setdefault("ROS_DOMAIN_ID", "43")
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return dict(env, **extra)


def main() -> None:
    """Run every transport ROUNDS times, print and record the table."""
    results: dict[str, list[ProbeResult]] = defaultdict(list)
    load_before = os.getloadavg()
    for round_index in range(ROUNDS):
        for name, extra in TRANSPORTS.items():
            try:
                result = run_probe(_env(extra), frames=FRAMES, timeout_s=120.0)
            except ProbeError as error:  # counted as nothing received, and said
                print(f"round {round_index + 1} {name}: {error}", flush=True)
                result = ProbeResult(0, FRAMES, 0, list(range(FRAMES)), np.nan, np.nan)
            results[name].append(result)
            print(f"round {round_index + 1} {name}: {result.received}/{result.expected}, "
                  f"latency median {result.latency_median_ms:.1f} ms, "
                  f"p95 {result.latency_p95_ms:.1f} ms", flush=True)  # fmt: skip
    load_after = os.getloadavg()

    def summary(name: str) -> tuple[float, float, float]:
        rs = results[name]
        received = float(np.mean([r.fraction for r in rs]))
        median = float(np.nanmedian([r.latency_median_ms for r in rs]))
        p95 = float(np.nanmedian([r.latency_p95_ms for r in rs]))
        return received, median, p95

    ref = summary(REFERENCE)
    lines = [
        "| transport | received (each round) | latency median ms | p95 ms | "
        "received ratio | median ratio | p95 ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in TRANSPORTS:
        received, median, p95 = summary(name)
        rounds = ", ".join(f"{r.received}/{r.expected}" for r in results[name])
        lines.append(
            f"| {name} | {rounds} | {median:.1f} | {p95:.1f} | {received / ref[0]:.2f} | "
            f"{median / ref[1]:.2f} | {p95 / ref[2]:.2f} |"
        )
    table = "\n".join(lines)
    print(table)
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    section = (
        f"{SECTION}\n\n{CONCLUSION}\n\nThis run: "
        f"`bench/bench_dds_transport.py`, {stamp}, {cpu_model()} ({os.cpu_count()} CPUs, "
        f"{platform.system()}), load average {load_before[0]:.1f} before / "
        f"{load_after[0]:.1f} after. {FRAMES} frames of 640×480 32FC1 (1.2 MB) at 30 Hz, "
        "reliable publisher → best-effort subscriber in another process (both through "
        f"`run_node`), {ROUNDS} rounds interleaved; latency = receive time − header stamp, "
        f"the median over rounds; ratios to the {REFERENCE}.\n\n{table}\n"
    )
    previous = _previous_run()
    if previous:
        section += f"\nThe run before:\n\n{previous}\n"
    replace_section(section, SECTION)


def _previous_run() -> str:
    """The last run's header line and table from docs/benchmarks.md ('' if none)."""
    text = BENCHMARKS.read_text(encoding="utf-8") if BENCHMARKS.exists() else ""
    if SECTION not in text:
        return ""
    body = text[text.index(SECTION) + len(SECTION):]
    body = body.split("\n## ", 1)[0].split("\nThe run before:", 1)[0]
    start = body.find("This run: ")
    return body[start + len("This run: "):].strip() if start >= 0 else ""


if __name__ == "__main__":
    main()
