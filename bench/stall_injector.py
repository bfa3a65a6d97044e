"""Stalls of the whole machine on purpose, for benchmarks of how a graph rides them out.

``--every`` seconds after the end of the last stall, one busy process per
core runs at nice -20 for ``--ms`` milliseconds (so one period is the two
added): beside it the graph's processes (nice 0) get ~1 % of
a core (CFS weights 88761 against 1024), so the stall is what a burst of
other work on a shared machine does, only known in length and time.
Without root the busy processes run at the highest nice allowed and say so.

Usage: python bench/stall_injector.py --ms 80 --every 5   (until SIGTERM / Ctrl-C)
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time


def _busy(until: float) -> None:
    try:
        os.nice(-20)
    except PermissionError:
        print("stall_injector: not root: the stall runs at nice 0", file=sys.stderr, flush=True)
    while time.monotonic() < until:
        pass


def stall(milliseconds: float, cores: int) -> None:
    """One busy process per core for ``milliseconds``; returns when all have ended."""
    until = time.monotonic() + milliseconds / 1e3
    children = []
    for _ in range(cores):
        pid = os.fork()
        if pid == 0:
            _busy(until)
            os._exit(0)
        children.append(pid)
    for pid in children:
        os.waitpid(pid, 0)


def main() -> int:
    """Stall every ``--every`` seconds until terminated; print how many stalls ran."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ms", type=float, required=True, help="length of each stall, ms")
    parser.add_argument("--every", type=float, default=5.0, help="seconds between stalls")
    parser.add_argument("--cores", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    if args.ms <= 0 or args.every < 0 or args.cores < 1:
        parser.error(f"--ms must be > 0, --every >= 0 and --cores >= 1, got {args.ms:g}, "
                     f"{args.every:g}, {args.cores}")
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    stalls = 0
    try:
        while True:
            time.sleep(args.every)
            stall(args.ms, args.cores)
            stalls += 1
    finally:
        print(f"stall_injector: {stalls} stalls of {args.ms:g} ms on {args.cores} cores",
              flush=True)


if __name__ == "__main__":
    sys.exit(main())
