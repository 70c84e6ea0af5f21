"""Soak run: `actuatord --sim` in real time for a while, sampling its memory. Prints the RSS at
start and end and actuatord's own loop statistics.

    python docs/soak.py --minutes 10
"""

import argparse
import subprocess
import sys
import time


def rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--minutes", type=float, default=10.0)
    args = parser.parse_args()
    seconds = args.minutes * 60
    proc = subprocess.Popen([sys.executable, "-m", "commands.actuatord", "--sim", "--duration",
                             str(seconds), "--no-multicast-scouting"], stdout=subprocess.PIPE,
                            text=True)
    proc.stdout.readline()
    time.sleep(5)
    samples = [(time.monotonic(), rss_kib(proc.pid))]
    while proc.poll() is None:
        time.sleep(10)
        if proc.poll() is None:
            samples.append((time.monotonic(), rss_kib(proc.pid)))
    out = proc.stdout.read().strip()
    start, end = samples[0][1], samples[-1][1]
    peak = max(r for _, r in samples)
    print(f"RSS after 5 s {start / 1024:.1f} MiB, at end {end / 1024:.1f} MiB, peak "
          f"{peak / 1024:.1f} MiB over {len(samples)} samples")
    print(out)


if __name__ == "__main__":
    main()
