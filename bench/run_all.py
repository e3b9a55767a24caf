"""`make bench`: every benchmark at reduced size (minutes on 2 cores); `--full` for full size.

Writes JSON and PNG charts to bench/out/; docs/results.md shows the latest of each.
"""

from __future__ import annotations

import subprocess
import sys
import time

BENCHES = ("error_vs_time", "stability", "accuracy", "engine_speed", "peer_smallppm", "error_estimation",
           "service_scaling", "merge_capacity")


def main() -> int:
    full = ["--full"] if "--full" in sys.argv[1:] else []
    for name in BENCHES:
        if name == "peer_smallppm":
            args = ["--sweep"] if full else []
        elif name == "merge_capacity":
            args = [] if full else ["--smoke"]
        else:
            args = [*full]
        t0 = time.perf_counter()
        print(f"== bench.{name} {' '.join(args)}", flush=True)
        subprocess.run([sys.executable, "-m", f"bench.{name}", *args], check=True)
        print(f"== bench.{name}: {time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
