#!/usr/bin/env python3
"""How many pages each running stage host touches in a short window.

For every `drivelab-host` process (or the PIDs given), clear its pages' referenced bits
(`/proc/PID/clear_refs`, which changes nothing but those bits), wait WINDOW_MS, and sum the
`Referenced:` lines of `/proc/PID/smaps`, by mapping. With a window of a few samples this is
about the set of pages one sample touches: on a CPU that empties the TLB at every switch
between processes (`drivelab doctor`, "address spaces"), each of them costs a page walk
whenever the host runs after another process. Three windows per process; the mappings are
those of the last one. Needs root. docs/measurements.md, "The TLB after a switch".

    python3 bench/tools/pages_touched.py WINDOW_MS [PID ...]
"""
import collections
import re
import subprocess
import sys
import time

HEADER = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) (\S+) \S+ \S+ \S+\s*(.*)$")


def referenced_kib(pid):
    by_mapping = collections.Counter()
    name = None
    with open(f"/proc/{pid}/smaps") as f:
        for line in f:
            m = HEADER.match(line)
            if m:
                path = m.group(4) or "[anonymous]"
                name = f"{path.split('/')[-1][:60]} {m.group(3)}"
            elif line.startswith("Referenced:"):
                by_mapping[name] += int(line.split()[1])
    return by_mapping


def process_name(pid):
    with open(f"/proc/{pid}/cmdline") as f:
        argv = f.read().split("\0")
    return argv[argv.index("--process") + 1] if "--process" in argv else str(pid)


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    window = float(sys.argv[1]) / 1000.0
    pids = [int(p) for p in sys.argv[2:]]
    if not pids:
        found = subprocess.run(["pgrep", "-x", "drivelab-host"], capture_output=True, text=True)
        pids = [int(p) for p in found.stdout.split()]
    if not pids:
        sys.exit("no drivelab-host is running (start a drive first, or give PIDs)")
    for pid in pids:
        windows = []
        for _ in range(3):
            with open(f"/proc/{pid}/clear_refs", "w") as f:
                f.write("1")
            time.sleep(window)
            windows.append(referenced_kib(pid))
        pages = [sum(w.values()) // 4 for w in windows]
        print(f"{process_name(pid)} (pid {pid}): pages referenced in {window * 1000:.1f} ms: {pages}")
        for mapping, kib in windows[-1].most_common(8):
            print(f"  {kib // 4:5d}  {mapping}")


if __name__ == "__main__":
    main()
